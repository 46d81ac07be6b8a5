"""On-robot drivers: processes that read sensors and push their frames to the console
(the push ingest protocol, docs/FORMATS.md; client helpers in :mod:`app.sources.push.clients`)."""
