"""The TOF's own turn, from its depth edges against a colour camera (fusion.drift_tof).

Ground truth: synthetic TOF frames whose mixed pixels are made the way a continuous-wave TOF
pixel mixes two surfaces (amplitude-weighted), and the simulated inspection room rendered
with the TOF (or a colour camera) turned by 0.3 degrees. Measured on the simulator (30
instants, docs/FINDINGS.md): one instant reads the TOF's turn within 0.02 degrees about x and
y and scatters by 0.05-0.09 about its optical axis; the true rig reads within 0.04. Hence
one instant's tolerances of 0.06 (x, y) and 0.2 (z), and six instants' 0.1 for the refined
rig (the issue's own).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.drift_support import TIMES_S, render, run, turned
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import rotation_angle_deg
from trifuse.fusion.drift import DriftCheck, refined_rig
from trifuse.fusion.drift_align import PairRotation
from trifuse.fusion.drift_tof import TofEdgeProbe, depth_edges


def mixed_frame(
    outline: float, fg_m: float = 2.0, bg_m: float = 5.0, a_fg: float = 400.0, a_bg: float = 100.0
) -> tuple[np.ndarray, np.ndarray]:
    """A 40 x 60 TOF frame: a foreground for x < ``outline`` (TOF pixels, centres at
    integers), the background beyond; the pixel the outline crosses mixes the two as a TOF
    pixel does (distance weighted by amplitude, amplitude averaged)."""
    x = np.arange(60, dtype=np.float64)
    f = np.clip(outline - (x - 0.5), 0.0, 1.0)  # the foreground's share of each pixel
    amp = f * a_fg + (1 - f) * a_bg
    d = (f * a_fg * fg_m + (1 - f) * a_bg * bg_m) / amp
    return np.tile(d, (40, 1)), np.tile(amp, (40, 1))


@pytest.mark.parametrize("outline", [20.3, 20.5, 20.9, 31.01])
def test_depth_edges_put_the_outline_where_the_mixed_pixel_says(outline: float) -> None:
    d, amp = mixed_frame(outline)
    e = depth_edges(d, amp)
    assert len(e) == 40  # one point a row, none along the columns (nothing changes there)
    np.testing.assert_allclose(e.x, outline, atol=1e-9)
    np.testing.assert_array_equal(e.y, np.arange(40))
    assert (e.axis == 0).all() and (e.side == -1).all()  # the foreground towards -x
    np.testing.assert_allclose(e.distance_m, 2.0)
    # transposed: found along the columns, the foreground towards -y
    t = depth_edges(d.T, amp.T)
    np.testing.assert_allclose(t.y, outline, atol=1e-9)
    assert (t.axis == 1).all() and (t.side == -1).all()
    # mirrored: the foreground towards +x
    m = depth_edges(d[:, ::-1], amp[:, ::-1])
    np.testing.assert_allclose(m.x, 59 - outline, atol=1e-9)
    assert (m.side == 1).all()


def test_depth_edges_without_amplitude_weigh_both_surfaces_equally() -> None:
    d, _ = mixed_frame(20.3, a_fg=100.0, a_bg=100.0)
    np.testing.assert_allclose(depth_edges(d, None).x, 20.3, atol=1e-9)


def test_no_outline_on_a_slope_a_small_step_or_invalid_pixels() -> None:
    x = np.arange(60, dtype=np.float64)
    slope = np.tile(2.0 + 0.06 * x, (40, 1))  # 3 % a pixel: neither side is flat
    assert len(depth_edges(slope)) == 0
    d, amp = mixed_frame(20.3, fg_m=2.0, bg_m=2.08)  # 4 %: below EDGE_REL
    assert len(depth_edges(d, amp)) == 0
    d, amp = mixed_frame(20.3)
    d[:, 19] = np.nan  # the foreground's flat pair is not there
    assert len(depth_edges(d, amp)) == 0


@pytest.fixture(scope="module")
def rig() -> Rig:
    return default_rig()


def probe_reading(rig: Rig, moved: Rig, camera: str = "ccd_left") -> np.ndarray:
    """One instant (6 s into the pan) rendered with ``moved``: the probe's rotation about the
    TOF's own axes, degrees."""
    ((_, fs),) = render(moved, (6.0,))
    grey = cv2.cvtColor(fs[camera].image, cv2.COLOR_RGB2GRAY)
    r = TofEdgeProbe(rig, "tof", camera).measure(fs["tof"].distance_m, fs["tof"].image, grey)
    assert isinstance(r, PairRotation), r
    assert r.work == "tof" and r.other == camera and r.patches >= 200
    return np.degrees(rig["tof"].T_rig_sensor[:3, :3].T @ r.theta)


def test_one_instant_reads_the_tofs_turn_and_a_cameras_turn_with_the_opposite_sign(
    rig: Rig,
) -> None:
    tol = np.array([0.06, 0.06, 0.2])
    assert (np.abs(probe_reading(rig, rig)) < tol).all()
    for turn in ((0.3, 0.0, 0.0), (0.0, 0.3, 0.0), (0.0, 0.0, 0.3)):
        got = probe_reading(rig, turned(rig, "tof", turn))
        assert (np.abs(got - turn) < tol).all(), (turn, got)
    # the camera turned instead: delta_tof - R_tof_cam delta_cam
    R_tof_cam = rig.T("tof", "ccd_right")[:3, :3]
    got = probe_reading(rig, turned(rig, "ccd_right", (0.0, 0.3, 0.0)), "ccd_right")
    want = -R_tof_cam @ np.array([0.0, 0.3, 0.0])
    assert (np.abs(got - want) < tol).all(), (want, got)


def test_a_tilted_tof_is_drifted_and_refined_within_a_tenth_of_a_degree(rig: Rig) -> None:
    """A tilt (about x) is the TOF's hardest turn: only outlines that are not upright show
    it. Six instants over the pan; the refined rig against the truth in the TOF's
    rotation to each camera (the TOF is the rig's reference: the refined rig keeps it at the
    origin and turns the others)."""
    truth = turned(rig, "tof", (0.3, 0.0, 0.0))
    report = run(rig, render(truth, TIMES_S))
    assert report.drifted == ["tof"], report.as_dict()
    s = report.sensors["tof"]
    assert np.linalg.norm(np.subtract(s.rotation_deg, (0.3, 0, 0))) < 0.1, s
    assert set(s.pairs) == {"ccd_left", "ccd_right"}
    refined = refined_rig(rig, report)
    for cam in ("ccd_left", "ccd_right", "thermal_left", "thermal_right"):
        R = refined.T(cam, "tof")[:3, :3].T @ truth.T(cam, "tof")[:3, :3]
        assert rotation_angle_deg(R) < 0.1, cam


def test_without_a_colour_camera_the_tof_is_undecided_with_the_reason(rig: Rig) -> None:
    frames = render(rig, TIMES_S[:2])
    thermal_only = [
        (t, {n: f for n, f in fs.items() if not n.startswith("ccd")}) for t, fs in frames
    ]
    check = DriftCheck(rig)
    for t, fs in thermal_only:
        check.measure(t, fs)
    tof = check.report().sensors["tof"]
    assert tof.verdict == "undecided" and "no frame of ccd_" in tof.reason, tof
