"""A simulated sensor that moves during a run (issue 34 item 3): the drift's spelling and
convention (app.sources.sim.drift), the inspection scenario rendering the moved sensor from
``at_s`` on, the simulated head never showing a picture of the other drift state (its
memory, live turning, disk cache and render process), and ``trifuse record --drift`` /
``trifuse serve --sim-drift``."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import WAIT_S, run_cli, small_rig, wait_until
from trifuse.app.sources.sim.drift import SensorDrift, moved_rig, parse_drift
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.app.sources.sim.pose_cache import pose_file, sample_poses, scenario_key
from trifuse.app.sources.sim.render import HeadModel
from trifuse.app.sources.sim.survey import SurveyScenario
from trifuse.app.sources.simulated import SimulatedHeadSource
from trifuse.calib.transforms import rotation_angle_deg, rvec_from_rotation

THERMALS = ["thermal_left", "thermal_right"]
"""The sensors the rendering tests render: the drifted one and another (cheap ones)."""
CHEAP = HeadModel(supersample={"color": 1, "thermal": 1, "tof": 1})
"""No edge supersampling: faster, and the pictures' quality is not what is tested."""


def _scenario(drift: SensorDrift | None = None, live: bool = True, **kw) -> InspectionScenario:
    return InspectionScenario(model=CHEAP, seed=3, live=live, drift=drift, **kw)


def _shift_px(a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal shift (px) of image ``b`` against ``a`` by phase correlation (Hann
    window, so that the borders do not take part)."""
    fa, fb = (np.ascontiguousarray(x, dtype=np.float32) for x in (a, b))
    window = cv2.createHanningWindow(fa.shape[::-1], cv2.CV_32F)
    return cv2.phaseCorrelate(fa, fb, window)[0][0]


# -- the drift: spelling and convention -------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "drift"),
    [
        ("thermal_left:0,0.3,0@20", SensorDrift("thermal_left", (0.0, 0.3, 0.0), 20.0)),
        ("thermal_left:0,0.3,0", SensorDrift("thermal_left", (0.0, 0.3, 0.0), 0.0)),
        (" tof : -0.25, 1e-3 ,2 @ 0.5 ", SensorDrift("tof", (-0.25, 0.001, 2.0), 0.5)),
        ("ccd_right:0.1,-0.2,0.05@0", SensorDrift("ccd_right", (0.1, -0.2, 0.05), 0.0)),
    ],
)
def test_a_drift_is_parsed_and_spelt_back(text: str, drift: SensorDrift) -> None:
    assert parse_drift(text) == drift
    assert parse_drift(str(drift)) == drift
    assert str(parse_drift(str(drift))) == str(drift)


def test_random_drifts_round_trip() -> None:
    rng = np.random.default_rng(34)
    for _ in range(50):
        rotation = tuple(float(x) for x in rng.normal(0.0, 0.5, 3))
        drift = SensorDrift("thermal_right", rotation, float(rng.uniform(0, 100)))  # type: ignore[arg-type]
        assert parse_drift(str(drift)) == drift


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("thermal_left", "no ':' after the sensor's name"),
        (":0,0.3,0", "no sensor name before ':'"),
        ("thermal_left:0,0.3", "the rotation '0,0.3' is not three finite numbers"),
        ("thermal_left:0,0.3,0,1", "is not three finite numbers"),
        ("thermal_left:0,x,0", "is not three finite numbers"),
        ("thermal_left:0,nan,0", "is not three finite numbers"),
        ("thermal_left:0,inf,0", "is not three finite numbers"),
        ("thermal_left:", "is not three finite numbers"),
        ("thermal_left:0,0.3,0@-1", "the start '-1' is not a number of seconds >= 0"),
        ("thermal_left:0,0.3,0@soon", "the start 'soon' is not a number of seconds >= 0"),
        ("thermal_left:0,0.3,0@inf", "is not a number of seconds >= 0"),
        ("thermal_left:0,0.3,0@", "the start '' is not"),
        ("thermal_left:0,0.3,0@1@2", "more than one '@'"),
    ],
)
def test_bad_drift_text_is_refused_with_what_was_expected(text: str, says: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_drift(text)
    message = str(info.value)
    assert message.startswith(f"sensor drift {text!r}: ")
    assert says in message and "expected SENSOR:RX,RY,RZ[@AT_S]" in message


@pytest.mark.parametrize(
    ("kwargs", "says"),
    [
        ({"sensor": "", "rotation_deg": (0, 0, 1)}, "expected a sensor name"),
        ({"sensor": "tof", "rotation_deg": (0, 1)}, "three finite numbers"),
        ({"sensor": "tof", "rotation_deg": (0, float("nan"), 1)}, "three finite numbers"),
        ({"sensor": "tof", "rotation_deg": (0, 0, 1), "at_s": -0.5}, "at_s: expected"),
    ],
)
def test_a_drift_checks_its_fields(kwargs: dict, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        SensorDrift(**kwargs)


def test_a_drift_is_active_from_its_start_on() -> None:
    drift = SensorDrift("tof", (0, 0, 1), 2.5)
    assert [drift.active(t) for t in (0.0, 2.4999, 2.5, 100.0)] == [False, False, True, True]
    assert SensorDrift("tof", (0, 0, 1)).active(0.0)
    assert hash(drift) == hash(SensorDrift("tof", (0.0, 0.0, 1.0), 2.5))  # a cache key


def test_moved_rig_turns_only_that_sensor_about_its_own_axes() -> None:
    """``T_rig_sensor_moved = T_rig_sensor @ [[R, 0], [0, 1]]``, ``R =
    cv2.Rodrigues(radians(rotation_deg))``: the turn's angle is the vector's length and
    its axis, in the sensor's frame, the vector's direction; the position stays."""
    rig = default_rig()
    rng = np.random.default_rng(7)
    for name in rig.names:
        rotation = rng.normal(0.0, 0.4, 3)
        drift = SensorDrift(name, tuple(rotation), 3.0)  # type: ignore[arg-type]
        moved = moved_rig(rig, drift)
        T0, T1 = rig[name].T_rig_sensor, moved[name].T_rig_sensor
        R_old_new = T0[:3, :3].T @ T1[:3, :3]  # the turn in the sensor's own frame
        assert rotation_angle_deg(R_old_new) == pytest.approx(np.linalg.norm(rotation), rel=1e-9)
        np.testing.assert_allclose(np.degrees(rvec_from_rotation(R_old_new)), rotation, atol=1e-9)
        np.testing.assert_array_equal(T1[:3, 3], T0[:3, 3])
        R = cv2.Rodrigues(np.radians(rotation))[0]
        np.testing.assert_allclose(T1, T0 @ np.block([[R, np.zeros((3, 1))], [0, 0, 0, 1]]))
        assert np.linalg.det(T1[:3, :3]) == pytest.approx(1.0)
        for other in rig.names:
            if other != name:
                assert moved[other] == rig[other]
        assert moved.reference == rig.reference and moved.eyes == rig.eyes
        assert moved.names == rig.names
    assert rig == default_rig()  # the rig given is not changed


def test_moved_rig_names_the_rigs_sensors_for_an_unknown_one() -> None:
    with pytest.raises(ValueError) as info:
        moved_rig(default_rig(), parse_drift("thermal_middle:0,0.3,0"))
    assert "no sensor 'thermal_middle' in the rig" in str(info.value)
    assert "tof, ccd_left, ccd_right, thermal_left, thermal_right" in str(info.value)
    with pytest.raises(ValueError, match="no sensor 'thermal_middle'"):
        _scenario(parse_drift("thermal_middle:0,0.3,0"))


# -- the inspection scenario ---------------------------------------------------------------


@pytest.mark.parametrize("live", [True, False], ids=["live", "accurate"])
def test_the_scenario_renders_the_moved_sensor_from_at_s_on(live: bool) -> None:
    """Before ``at_s`` the frames are the undrifted scenario's; from it on the drifted
    sensor's are those of the scenario built with the moved rig, the other sensor's (and
    its truth) unchanged; ``rig`` stays the calibrated rig."""
    drift = SensorDrift("thermal_left", (0.0, 1.0, 0.0), 1.0)
    plain, drifted = _scenario(live=live), _scenario(drift, live=live)
    moved = _scenario(live=live, rig=moved_rig(plain.rig, drift))
    assert drifted.rig == plain.rig and drifted.rig_at(0.5) is drifted.rig
    assert drifted.rig_at(1.0) is drifted.drifted_rig and drifted.drifted_rig == moved.rig
    before, _ = plain.render(0.5, THERMALS)
    got, _ = drifted.render(0.5, THERMALS)
    for name in THERMALS:
        np.testing.assert_array_equal(got[name].image, before[name].image)
    after, after_truth = plain.render(1.5, THERMALS)
    got, got_truth = drifted.render(1.5, THERMALS)
    want, want_truth = moved.render(1.5, THERMALS)
    np.testing.assert_array_equal(got["thermal_left"].image, want["thermal_left"].image)
    np.testing.assert_array_equal(
        got_truth["thermal_left"].range_m, want_truth["thermal_left"].range_m
    )
    np.testing.assert_array_equal(got["thermal_right"].image, after["thermal_right"].image)
    np.testing.assert_array_equal(
        got_truth["thermal_right"].range_m, after_truth["thermal_right"].range_m
    )
    # The sensor turned right (+y, its own down axis): the room moves left in its image,
    # by fx tan(1 deg) near the middle.
    fx = plain.rig["thermal_left"].intrinsics.fx
    shift = _shift_px(after["thermal_left"].image, got["thermal_left"].image)
    assert shift == pytest.approx(-fx * np.tan(np.radians(1.0)), rel=0.15)
    # drifted= renders either state whatever the time
    early, _ = drifted.render(0.5, ["thermal_left"], drifted=True)
    np.testing.assert_array_equal(
        early["thermal_left"].image, moved.render(0.5, ["thermal_left"])[0]["thermal_left"].image
    )
    late, _ = drifted.render(1.5, ["thermal_left"], drifted=False)
    np.testing.assert_array_equal(late["thermal_left"].image, after["thermal_left"].image)
    with pytest.raises(ValueError, match="no sensor drift"):
        plain.render(0.5, ["thermal_left"], drifted=True)


def test_survey_cache_key_and_default_key_include_the_drift() -> None:
    drift = parse_drift("thermal_left:0,0.3,0@20")
    plain, drifted = SurveyScenario(model=CHEAP), SurveyScenario(model=CHEAP, drift=drift)
    assert plain.cache_key() != drifted.cache_key() and repr(drift) in drifted.cache_key()
    assert "drift" not in plain.cache_key()
    default = scenario_key(_scenario(), 0)
    assert default == "InspectionScenario(seed=0, live=True)"  # as before: no drift
    assert scenario_key(_scenario(drift), 0) != default
    folder = Path("cache")
    assert pose_file(folder, 1.5, True) != pose_file(folder, 1.5)


def test_pose_samples_before_and_after_the_drift_never_share() -> None:
    """Samples of equal head poses share one rendering in each drift state, never across;
    a sample no time before ``at_s`` shows has no undrifted pose."""
    scenario = _scenario(SensorDrift("thermal_left", (0, 0.3, 0), 3.0), pan_period_s=10.0)
    plain = sample_poses(_scenario(pan_period_s=10.0), 20, 2.0)
    got = sample_poses(scenario, 20, 2.0)
    assert plain.drifted_sample_pose is None and not any(plain.pose_drifted)
    assert got.drifted_sample_pose is not None
    for j, t in enumerate(got.sample_t):
        after = got.drifted_sample_pose[j]
        assert got.pose_drifted[after]
        before = got.sample_pose[j]
        assert got.pose_drifted[before] == (t > 3.25)  # no time before 3 s shows sample 7 on
    undrifted = {got.sample_pose[j] for j in range(7)}
    assert undrifted.isdisjoint(got.drifted_sample_pose)
    # the head swings back: equal poses are shared within a state as without the drift
    assert len(set(got.drifted_sample_pose)) == len(set(plain.sample_pose))
    # from the start: no undrifted pose at all
    at_start = sample_poses(_scenario(SensorDrift("thermal_left", (0, 0.3, 0))), 20, 2.0)
    assert all(at_start.pose_drifted)


# -- the simulated head ----------------------------------------------------------------------


def _thermal_left_frames(src: SimulatedHeadSource) -> dict[int, np.ndarray]:
    return {f.stamp_ns: f.image for f in src.frames() if f.sensor == "thermal_left"}


def test_the_simulated_head_shows_the_moved_picture_from_at_s_on_and_keeps_it() -> None:
    """Samples of equal head pose before and after ``at_s`` do not share a rendering; the
    drift stays when the stream loops (the head pose at 2 s is that of 0 s)."""
    drift = SensorDrift("thermal_left", (0.0, 1.0, 0.0), 1.0)
    scenario = _scenario(drift, pan_period_s=2.0)
    rates = {"thermal": 2.0}
    with SimulatedHeadSource(
        scenario,
        sensors=THERMALS,
        rates_hz=rates,
        render_hz=2.0,
        duration_s=3.0,
        wait_for_render=True,
        cache_dir=False,
        render_process=False,
    ) as src:
        assert src.rig is scenario.rig
        frames = {(f.sensor, f.stamp_ns): f.image for f in src.frames() if f.sensor in THERMALS}
        truths = {stamp: src.truth_at(stamp, []) for _, stamp in frames}
    assert truths[500_000_000].rig is scenario.rig
    assert truths[2_000_000_000].rig is scenario.drifted_rig
    check = _scenario(drift, pan_period_s=2.0)
    for (name, stamp), image in frames.items():
        t = stamp / 1e9
        # the pose shown: the loop's sample of the stamp, rendered at its first sample's time
        assert truths[stamp].pose_t_s in {(round(t * 2) % 4) / 2, 0.0}
        want = check.render(truths[stamp].pose_t_s, [name], drifted=t >= 1.0)[0][name].image
        np.testing.assert_array_equal(image, want, err_msg=f"{name} at {t} s")
    # 0 s and 2 s: the same head pose and sample; the drifted sensor differs, the other not
    assert not np.array_equal(frames["thermal_left", 0], frames["thermal_left", 2_000_000_000])
    np.testing.assert_array_equal(
        frames["thermal_right", 0], frames["thermal_right", 2_000_000_000]
    )


class _HeldScenario:
    """A drifted scenario whose renders wait until ``release`` is set where ``held(t_s,
    drifted)`` says (default: the drifted state's): the source has the other poses and
    nothing of those meanwhile."""

    def __init__(self, inner: InspectionScenario, held=None) -> None:
        self.inner = inner
        self.rig, self.drift, self.drifted_rig = inner.rig, inner.drift, inner.drifted_rig
        self.pan_period_s = inner.pan_period_s
        self.release = threading.Event()
        self.held = held or (lambda t_s, drifted: drifted)

    def T_world_rig(self, t_s: float) -> np.ndarray:
        return self.inner.T_world_rig(t_s)

    def render(self, t_s: float, sensors: list[str] | None = None, *, drifted: bool | None = None):
        state = self.inner.drift_active(t_s) if drifted is None else drifted
        if self.held(t_s, state):
            assert self.release.wait(WAIT_S), "test: the held render was never released"
        return self.inner.render(t_s, sensors, drifted=drifted)


def test_live_mode_never_turns_a_picture_of_the_other_drift_state() -> None:
    """Live mode turns the nearest rendered pose while a pose is not rendered yet, but
    only one of the same drift state: with none, the frame waits for its own rendering."""
    drift = SensorDrift("thermal_left", (0.0, 1.0, 0.0), 1.0)
    held = _HeldScenario(_scenario(drift, pan_period_s=4.0))
    src = SimulatedHeadSource(
        held,
        sensors=THERMALS,
        rates_hz={"thermal": 4.0},
        render_hz=2.0,
        live=True,
        cache_dir=False,
        render_process=False,
    )
    got: dict[int, np.ndarray] = {}
    done = threading.Event()

    def consume() -> None:
        for f in src.frames():
            if f.sensor == "thermal_left":
                got[f.stamp_ns] = f.image
                if f.stamp_ns >= 1_500_000_000:
                    break
        done.set()

    thread = threading.Thread(target=consume, daemon=True)
    try:
        assert src.wait_ready(WAIT_S)
        thread.start()
        # Before 1 s: rendered or turned from an undrifted pose; at 1 s the frame waits
        # (the render thread renders sample 1, then waits at the drifted sample 2).
        wait_until(lambda: 750_000_000 in got, "the frames before the drift")
        assert not done.wait(1.0) and max(got) == 750_000_000
        held.release.set()
        assert done.wait(WAIT_S)
    finally:
        held.release.set()
        src.close()
    check = _scenario(drift, pan_period_s=4.0)
    fx = check.rig["thermal_left"].intrinsics.fx
    for stamp in (1_000_000_000, 1_500_000_000):  # rendered at 1 s; at 1.5 s maybe turned
        t = stamp / 1e9
        want = check.render(t, ["thermal_left"], drifted=True)[0]["thermal_left"].image
        plain = check.render(t, ["thermal_left"], drifted=False)[0]["thermal_left"].image
        assert abs(_shift_px(want, got[stamp])) < 0.5, t
        assert _shift_px(plain, got[stamp]) == pytest.approx(-fx * np.tan(np.radians(1)), rel=0.2)
    want = check.render(1.0, ["thermal_left"], drifted=True)[0]["thermal_left"].image
    np.testing.assert_array_equal(got[1_000_000_000], want)


def test_live_mode_turns_a_drifted_pose_about_the_moved_sensors_axes() -> None:
    """A drifted pose not rendered yet is the nearest drifted one turned by the head's turn
    as the moved sensor sees it (a sensor rolled 20 degrees sees the pan about another
    axis than the calibrated one): the turned picture is where the rendering puts it."""
    drift = SensorDrift("thermal_left", (0.0, 0.0, 20.0))
    held = _HeldScenario(_scenario(drift, pan_period_s=4.0), lambda t_s, drifted: t_s > 0)
    src = SimulatedHeadSource(
        held,
        sensors=["thermal_left"],
        rates_hz={"thermal": 2.0},
        render_hz=2.0,
        live=True,
        cache_dir=False,
        render_process=False,
    )
    try:
        assert src.wait_ready(WAIT_S)
        frames = {}
        for f in src.frames():  # pose 1 (0.5 s) is held: turned from pose 0
            frames[f.stamp_ns] = f.image
            if f.stamp_ns >= 500_000_000:
                break
        assert src.rendered_count == 1 and src.provisional_made >= 1
    finally:
        held.release.set()
        src.close()
    real = held.inner.render(0.5, ["thermal_left"])[0]["thermal_left"].image
    first, turned = frames[0], frames[500_000_000]
    fa, fb, fc = (np.ascontiguousarray(x, dtype=np.float32) for x in (real, turned, first))
    window = cv2.createHanningWindow(fa.shape[::-1], cv2.CV_32F)
    assert np.hypot(*cv2.phaseCorrelate(fa, fb, window)[0]) < 0.5
    assert np.hypot(*cv2.phaseCorrelate(fa, fc, window)[0]) > 20  # 14 degrees of pan


def test_the_disk_cache_keeps_drifted_poses_apart(tmp_path: Path) -> None:
    """A drifted survey's poses go to their own files, and a second source reads them back
    as rendered: the moved picture after ``at_s``, the calibrated one before."""
    drift = SensorDrift("thermal_left", (0.0, 1.0, 0.0), 0.5)
    kw = dict(sensors=["thermal_left"], render_hz=2.0, loop_s=1.0, wait_for_render=True)

    def run() -> tuple[dict[int, np.ndarray], Path]:
        scenario = SurveyScenario(model=CHEAP, seed=3, live=True, drift=drift)
        with SimulatedHeadSource(
            scenario, duration_s=2.0, rates_hz={"thermal": 2.0}, cache_dir=tmp_path, **kw
        ) as src:
            frames = _thermal_left_frames(src)
            wait_until(lambda: src.rendered_count == src.pose_count == 4, "every pose")
            assert src.cache_dir is not None
            return frames, src.cache_dir

    first, folder = run()
    assert sorted(p.name for p in folder.iterdir()) == [
        "pose-0us-drifted.npz",
        "pose-0us.npz",
        "pose-500000us-drifted.npz",
        "pose-500000us.npz",
    ]
    again, folder_again = run()
    assert folder_again == folder and first.keys() == again.keys()
    for stamp in first:
        np.testing.assert_array_equal(first[stamp], again[stamp])
    assert not np.array_equal(first[0], first[1_000_000_000])  # sample 0 before and after
    plain = SurveyScenario(model=CHEAP, seed=3, live=True)
    with SimulatedHeadSource(
        plain, duration_s=1.0, rates_hz={"thermal": 2.0}, cache_dir=tmp_path, **kw
    ) as src:
        assert src.cache_dir is not None and src.cache_dir != folder
        np.testing.assert_array_equal(_thermal_left_frames(src)[0], first[0])


def test_the_render_process_renders_the_default_scenarios_drift(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The default scenario with ``drift=``: rendered in the render process, its files in
    its own cache folder, the moved picture after ``at_s``."""
    monkeypatch.setenv("TRIFUSE_SIM_CACHE", str(tmp_path))
    drift = SensorDrift("thermal_left", (0.0, 1.0, 0.0), 0.5)
    with SimulatedHeadSource(
        sensors=["thermal_left"],
        rates_hz={"thermal": 2.0},
        render_hz=2.0,
        loop_s=1.0,
        duration_s=1.5,
        wait_for_render=True,
        render_process=True,
        live=True,
        seed=3,
        drift=drift,
    ) as src:
        assert src.render_process and src.cache_dir is not None
        frames = _thermal_left_frames(src)
        names = sorted(p.name for p in src.cache_dir.iterdir())
    assert "pose-500000us-drifted.npz" in names and "pose-0us.npz" in names
    check = InspectionScenario(seed=3, live=True, drift=drift)
    for stamp, image in frames.items():
        t = stamp / 1e9
        want = check.render((round(t * 2) % 2) / 2, ["thermal_left"], drifted=t >= 0.5)[0]
        np.testing.assert_array_equal(image, want["thermal_left"].image, err_msg=str(t))
    with pytest.raises(ValueError, match="drift: for the default scenario"):
        SimulatedHeadSource(_scenario(), drift=drift)


# -- the command line ------------------------------------------------------------------------


def _thermal_frames(path: Path) -> dict[tuple[str, int], np.ndarray]:
    from trifuse.app.recording.reader import ReplaySource

    with ReplaySource(path, realtime=False) as src:
        return {(f.sensor, f.stamp_ns): f.image for f in src.frames() if f.sensor in THERMALS}


@pytest.fixture(scope="module")
def small_rig_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from trifuse.app.storage.rigfile import save_rig

    return save_rig(tmp_path_factory.mktemp("rig") / "rig.yaml", small_rig())


@pytest.mark.parametrize(
    ("exact", "duration_s", "at_s"), [(False, 0.8, 0.4), (True, 0.2, 0.1)], ids=["live", "exact"]
)
def test_record_sim_drift(
    exact: bool,
    duration_s: float,
    at_s: float,
    small_rig_path: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``record --source sim --drift``: from ``at_s`` on the drifted sensor's frames are
    those of a recording of the moved rig, before it those of the calibrated rig; the
    other sensor's never change; the metadata says the drift and the moved pose; the rig
    stored is the calibrated one."""
    from trifuse.app.recording.reader import ReplaySource
    from trifuse.app.storage.rigfile import load_rig, save_rig

    rig = load_rig(small_rig_path)
    spec = f"thermal_left:0,2,0@{at_s:g}"
    moved_path = save_rig(tmp_path / "moved.yaml", moved_rig(rig, parse_drift(spec)))
    argv = ["record", "--source", "sim", "--duration", str(duration_s), "--seed", "3"]
    argv += ["--exact"] if exact else []
    outs = {k: tmp_path / f"{k}.mcap" for k in ("plain", "drift", "moved")}
    for what, extra in [
        ("plain", ["--rig", str(small_rig_path)]),
        ("drift", ["--rig", str(small_rig_path), "--drift", spec]),
        ("moved", ["--rig", str(moved_path)]),
    ]:
        code, out, err = run_cli([*argv, *extra, "--out", str(outs[what])], capsys)
        assert code == 0, err
        if what == "drift":
            assert (
                f"thermal_left turned by (0, 2, 0) deg about its own axes from {at_s:g} s on" in out
            )
    plain, drifted, moved = (_thermal_frames(outs[k]) for k in ("plain", "drift", "moved"))
    assert plain.keys() == drifted.keys() == moved.keys()
    stamps = {stamp for _, stamp in plain}
    assert min(stamps) < at_s * 1e9 <= max(stamps)
    for (name, stamp), image in drifted.items():
        after = name == "thermal_left" and stamp >= at_s * 1e9
        np.testing.assert_array_equal(image, (moved if after else plain)[name, stamp])
        if after:
            assert not np.array_equal(image, plain[name, stamp]), stamp
    with ReplaySource(outs["drift"], realtime=False) as src:
        assert src.rig == rig
        meta = src.index.metadata["trifuse.simulation"]
    assert meta["drift"] == spec and meta["scenario"] == "inspection" and meta["seed"] == "3"
    assert meta["mode"] == ("exact" if exact else "live")
    T = np.array([float(x) for x in meta["drift_T_rig_sensor"].split(",")]).reshape(4, 4)
    np.testing.assert_array_equal(T, moved_rig(rig, parse_drift(spec))["thermal_left"].T_rig_sensor)
    with ReplaySource(outs["plain"], realtime=False) as src:
        assert "drift" not in src.index.metadata["trifuse.simulation"]


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["record", "--source", "sim", "--drift", "thermal_left"], "no ':' after"),
        (["record", "--source", "sim", "--drift", "thermal_left:0,1"], "not three finite"),
        (["record", "--source", "sim", "--drift", "thermal_left:0,0,1@-2"], "seconds >= 0"),
        (["record", "--source", "sim", "--drift", "nope:0,0,1"], "no sensor 'nope' in the rig"),
        (["record", "--source", "replay:x.mcap", "--drift", "tof:0,0,1"], "goes with --source sim"),
    ],
)
def test_record_drift_usage_errors(
    argv: list[str], says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run_cli([*argv, "--out", str(tmp_path / "o.mcap")], capsys)
    assert code == 2 and says in err, err
    assert err.startswith("trifuse record: ") and len(err.strip().splitlines()) == 1
    if "replay" not in argv[2]:
        assert "--drift: sensor drift" in err
    assert not (tmp_path / "o.mcap").exists()


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--sim-drift", "thermal_left"], "--sim-drift: sensor drift 'thermal_left': no ':'"),
        (["--sim-drift", "thermal_middle:0,0,1"], "no sensor 'thermal_middle' in the rig"),
        (["--sim-drift", "tof:0,0,1", "--replay", "x.mcap"], "for the simulated head only"),
        (["--sim-drift", "tof:0,0,1", "--push"], "for the simulated head only"),
        (
            ["--sim-drift", "tof:0,0,1", "--scenario", "calibration"],
            "--sim-drift goes with --scenario inspection or survey",
        ),
    ],
)
def test_serve_sim_drift_usage_errors(
    argv: list[str], says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    workdir = tmp_path / "work"
    code, _, err = run_cli(["serve", *argv, "--port", "0", "--workdir", str(workdir)], capsys)
    assert code == 2 and says in err, err
    assert err.startswith("trifuse serve: ") and len(err.strip().splitlines()) == 1
    assert not workdir.exists()  # refused before anything started


def test_open_source_gives_the_simulated_head_its_drift(monkeypatch: pytest.MonkeyPatch) -> None:
    """``serve --sim-drift``'s source: the scenario with the drift (the source's rig the
    calibrated one); refused for the calibration scenario and other sources."""
    from trifuse.app.recording.open_source import open_source, simulated_source

    monkeypatch.setenv("TRIFUSE_SIM_CACHE", "off")  # keep the shared disk cache as it is
    drift = parse_drift("thermal_left:0,0.3,0@20")
    with pytest.raises(ValueError, match="not calibration"):
        simulated_source("calibration", drift=drift)
    with pytest.raises(ValueError, match="for the simulated head only"):
        open_source(push=True, drift=drift)
    opened = open_source(scenario="survey", drift=drift)
    try:
        scenario = opened.source.scenario  # type: ignore[attr-defined]
        assert isinstance(scenario, SurveyScenario) and scenario.drift == drift
        assert opened.rig == default_rig() and opened.ground_truth_rig == default_rig()
        assert "thermal_left turned by (0, 0.3, 0) deg from 20 s on" in opened.description
    finally:
        opened.source.close()
