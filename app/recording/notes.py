"""Reading a recording's measurement notes (issue 35): the alarm events and the measurement
settings the console wrote on :data:`~app.recording.layout.MEASUREMENTS_TOPIC` while it
recorded (docs/FORMATS.md "Measurement notes"; written by
:meth:`app.recording.writer.RecordingWriter.write_note`)."""

from __future__ import annotations

import json
from pathlib import Path

from mcap_protobuf.decoder import DecoderFactory

from trifuse.app.recording.layout import MEASUREMENTS_TOPIC
from trifuse.app.recording.mcapindex import McapDamage, McapIndex
from trifuse.app.recording.writer import Note

_LEVELS = {2: "info", 3: "warning"}  # foxglove.Log's INFO and WARNING


def read_notes(path: str | Path) -> list[Note]:
    """The notes of the recording at ``path`` in the order written (those before damage in
    a damaged file; a note that does not decode is left out). RecordingError: no MCAP."""
    index = McapIndex.open(path)
    notes: list[Note] = []
    try:
        decoders = DecoderFactory()
        for ref in index.chunks:
            for message in index.read_chunk(ref):
                channel = index.channels[message.channel_id]
                if channel.topic != MEASUREMENTS_TOPIC:
                    continue
                schema = index.schema_of(channel)
                decode = (
                    None
                    if schema is None
                    else decoders.decoder_for(channel.message_encoding, schema)
                )
                if decode is None:
                    continue
                try:
                    msg = decode(message.data)
                    body = json.loads(msg.message)
                except Exception:
                    continue
                level = _LEVELS.get(int(msg.level), "info")
                notes.append(Note(message.log_time, msg.name, level, body))
    except McapDamage:
        pass  # the notes before the damage
    finally:
        index.close()
    return notes
