"""Push ingest: on-robot drivers send frames to the console over a WebSocket.

The parts (import each name from its module; this package re-exports nothing):

- :mod:`~app.sources.push.protocol`: the wire protocol (message layout, limits, the
  header, :class:`~app.sources.push.protocol.PushError`); docs/FORMATS.md, "Push ingest
  protocol", describes it for driver writers.
- :mod:`~app.sources.push.encode`: images and frames to messages (the driver's side).
- :mod:`~app.sources.push.decode`: messages checked and decoded to frames (the console's
  side).
- :mod:`~app.sources.push.source`: :class:`~app.sources.push.source.PushSource`, the
  :class:`~app.sources.base.FrameSource` whose frames are the pushed ones.
- :mod:`~app.sources.push.router`: the ``/ingest`` WebSocket endpoint for the console's
  FastAPI app (the only part that imports FastAPI) and uvicorn's message limit.
- :mod:`~app.sources.push.clients`: :class:`~app.sources.push.clients.PushClient`
  (blocking) and :class:`~app.sources.push.clients.AsyncPushClient`.

A driver needs numpy, OpenCV and ``websockets``.
"""
