"""The Fusion panel's "Video stream (new viewers)" dropdown (a real Viser server): it sets the
console's default preset and follows a change made through ``/api/stream/settings``."""

from __future__ import annotations

from trifuse.app.server.panels.stream import AUTO_LABEL, StreamPresetControl, preset_labels
from trifuse.app.server.runtime.video_presets import PRESETS, StreamSettings


def test_labels_name_every_preset_with_its_level() -> None:
    labels = preset_labels()
    assert list(labels) == list(PRESETS)
    assert labels["auto"] == AUTO_LABEL
    assert labels["8"] == "8 Mbit/s (2560x960, 30 fps)"
    assert labels["1"] == "1 Mbit/s (1280x480, 15 fps)"
    assert len(set(labels.values())) == len(labels)


def test_dropdown_sets_and_follows_the_default_preset(server) -> None:
    settings = StreamSettings("2")
    control = StreamPresetControl(server.gui, settings)
    assert control.dropdown.value == "2 Mbit/s (1280x480, 25 fps)"  # starts at the setting
    assert control.dropdown.options == tuple(preset_labels().values())
    control.dropdown.value = "4 Mbit/s (1920x720, 30 fps)"  # the operator picks a preset
    assert settings.preset == "4"
    control.dropdown.value = AUTO_LABEL
    assert settings.preset == "auto"
    settings.preset = "1"  # PUT /api/stream/settings
    control.follow()
    assert control.dropdown.value == "1 Mbit/s (1280x480, 15 fps)" and settings.preset == "1"


def test_a_choice_from_the_browser_survives_a_follow_before_its_callback(server) -> None:
    """Viser stores a browser's dropdown choice first and runs the choice's callback after
    (in another thread); the panel's follow in between must not write the old preset back,
    or the operator's choice is lost."""
    settings = StreamSettings("2")
    control = StreamPresetControl(server.gui, settings)
    control.dropdown._impl.value = "4 Mbit/s (1920x720, 30 fps)"  # viser's first step
    control.follow()  # the console's tick runs before the callback
    assert control.dropdown.value == "4 Mbit/s (1920x720, 30 fps)"
    for callback in control.dropdown._impl.update_cb:  # viser's second step
        callback(None)
    assert settings.preset == "4"
    settings.preset = "1"  # and a change through the API is still shown
    control.follow()
    assert control.dropdown.value == "1 Mbit/s (1280x480, 15 fps)"
