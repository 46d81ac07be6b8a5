"""The console's video stream control: the default preset of new viewers, in the Fusion panel.

A dropdown bound to ``ctx.stream_settings.preset`` (the setting ``/api/stream/settings``
reads and writes): a viewer that asks ``/stream.video`` for no preset, and the viewer page
of an operator who never picked one, get this preset. Viewers already connected keep theirs.
"""

from __future__ import annotations

from typing import Any

from trifuse.app.server.runtime.video_presets import LEVELS, PRESETS, StreamSettings

AUTO_LABEL = "auto (follows the link)"


def preset_labels() -> dict[str, str]:
    """Each preset of :data:`PRESETS` -> its dropdown label, e.g. ``"4"`` ->
    ``"4 Mbit/s (1920x720, 30 fps)"``."""
    labels = {"auto": AUTO_LABEL}
    for lv in LEVELS:
        labels[lv.name] = f"{lv.max_bps / 1e6:g} Mbit/s ({lv.size[0]}x{lv.size[1]}, {lv.fps} fps)"
    return {p: labels[p] for p in PRESETS}


class StreamPresetControl:
    """The dropdown "Video stream (new viewers)" in the GUI folder open when built.

    Args:
        gui: the Viser server's ``gui`` (its ``add_dropdown``).
        settings: the console-wide stream settings it shows and sets.
    """

    def __init__(self, gui: Any, settings: StreamSettings) -> None:
        self.settings = settings
        self.labels = preset_labels()
        self._presets = {label: p for p, label in self.labels.items()}
        self.dropdown = gui.add_dropdown(
            "Video stream (new viewers)",
            tuple(self.labels.values()),
            initial_value=self.labels[settings.preset],
            hint="The viewer's H.264 stream: auto adapts bitrate and picture size to the "
            "link; a preset caps it. Each viewer may pick another (its Stream select).",
        )
        self._shown = settings.preset
        self.dropdown.on_update(lambda _event: self.apply())

    def apply(self) -> None:
        """The dropdown's preset becomes the console's default."""
        self.settings.preset = self._shown = self._presets[self.dropdown.value]

    def follow(self) -> None:
        """Show the setting if it changed elsewhere (``/api/stream/settings``). A dropdown
        that merely differs is left alone: Viser sets its value before the choice's callback
        runs, and writing the old preset back in between would lose the operator's choice."""
        preset = self.settings.preset
        if preset != self._shown:
            self._shown = preset
            self.dropdown.value = self.labels[preset]
