"""Issue 4's "must show" ranging claims on simulated frames (``iscd eval --suite ranging``).

Single LED, PWM-8, b = 0.6 m, f/4, right camera slightly defocused (0.3 px), independent air
jitter 0.05 px RMS per camera, textured background. The receiver's decoder finds and tracks
the LED; every method of iscd.decode.ranging.estimators.METHODS ranges the same patches of the same
frames; per-frame errors against the true distance on the frames where the LED is lit
(all of them, and the frames every ranger emits: those that pass the common spot-SNR
gate).
1000 frames a point by default, 5000 (as in the dissertation) under ``slow``. Seeds are
those of ``iscd eval --seed 1``. Unmet targets stay as targets, marked xfail(strict=True)
with the measured value.
"""

from __future__ import annotations

from functools import lru_cache

import pytest

from fakes import xfail_where
from iscd.core.config import default_config
from iscd.eval.suites import RANGING_DISTANCES_M, jitter_floor_mae, point_seed, ranging_cfg
from iscd.eval.report import is_project_method
from iscd.eval.sweeps import RangingResult, run_ranging

TARGET_M = {30.0: 0.05, 60.0: 0.15}


@lru_cache(maxsize=None)
def _point(distance_m: float, frames: int) -> RangingResult:
    cfg = ranging_cfg(default_config(), distance_m, point_seed(1, "ranging", distance_m))
    res = run_ranging(cfg, frames)
    floor = jitter_floor_mae(cfg)
    mine = res.stats(res.project_method).mae
    print(f"\n{distance_m:g} m, {res.frames.size} frames scored, jitter floor {floor:.4f} m, "
          f"project method {res.project_method}")
    em = res.stats_emitted(res.project_method).mae
    print(f"  emitted by every ranger: {100 * res.emitted_by_all().mean():.2f} % of the scored frames")
    for m in res.errors_m:
        s, e = res.stats(m), res.stats_emitted(m)
        print(f"  {m:21s} MAE {s.mae:.4f}  bias {s.bias:+.4f}  RMSE {s.rmse:.4f}  "
              f"{res.project_method}/{m} {mine / s.mae:.2f}  | emitted: MAE {e.mae:.4f} RMSE {e.rmse:.4f} "
              f"ratio {em / e.mae:.2f}")
    return res


def _peers(res: RangingResult) -> list[str]:
    return [m for m in res.errors_m if not is_project_method(m)]


@pytest.mark.parametrize("distance_m", [30.0, 60.0])
def test_project_method_per_frame_mae_target(distance_m: float) -> None:
    """Per-frame MAE <= 0.05 m at 30 m and <= 0.15 m at 60 m with the project's method (the
    live pipeline's ``[ranging]`` default)."""
    res = _point(distance_m, 1000)
    s = res.stats(res.project_method)
    assert s.failed == 0 and s.n >= 700
    assert s.mae <= TARGET_M[distance_m]


def _ratios(res: RangingResult) -> dict[str, float]:
    """MAE of the project's method / each peer's, on the frames every ranger emits (the
    same frames for all: those passing the common spot-SNR gate, >= 99.5 % of them)."""
    assert res.emitted_by_all().mean() >= 0.995
    mine = res.stats_emitted(res.project_method).mae
    return {m: mine / res.stats_emitted(m).mae for m in _peers(res)}


@pytest.mark.parametrize("distance_m", [30.0, 60.0])
def test_project_method_below_every_peer(distance_m: float) -> None:
    """On the same frames the project's MAE is below each peer's (ratios printed), on the
    frames the rangers emit and on every scored frame."""
    res = _point(distance_m, 1000)
    ratios = _ratios(res)
    assert {"dissertation", "dissertation-literal", "poc", "cv2", "skimage", "centroid"} <= set(ratios)
    assert all(r < 1.0 for r in ratios.values()), ratios
    mine = res.stats(res.project_method).mae
    assert all(mine < res.stats(m).mae for m in _peers(res))


def test_the_dissertations_method_reproduces_fig_3_7() -> None:
    """The dissertation's method (bicubic x3 + POC + sinc fit), in the same table, stays below
    0.5 m out to 60 m and beats conventional POC at 60 m, as in fig. 3.7."""
    for d in (30.0, 60.0):
        res = _point(d, 1000)
        assert {"dissertation", "dissertation-literal", "poc"} <= set(res.errors_m)
        assert res.stats("dissertation").mae < 0.5
    far = _point(60.0, 1000)
    assert far.stats("dissertation").mae < far.stats("poc").mae


def test_errors_are_against_truth_and_above_the_jitter_floor() -> None:
    """A sanity check of the harness: no method can beat the error the air jitter alone causes
    by much (the truth is the geometric distance, the frames are jittered), and the errors
    grow with distance roughly as Z^2 (dZ/dd)."""
    near, far = _point(30.0, 1000), _point(60.0, 1000)
    for res, d in ((near, 30.0), (far, 60.0)):
        floor = jitter_floor_mae(ranging_cfg(default_config(), d, 1))
        best = min(res.stats(m).mae for m in res.errors_m)
        assert best > 0.8 * floor
        assert abs(res.z_true_m.mean() - d) < 1e-6
    assert far.stats("dissertation").mae > 2.5 * near.stats("dissertation").mae


SLOW_MAE: dict[float, str] = {}
SLOW_PEERS = {25.0: (
    "measured at 25 m, seed 1, 5000 frames, on the frames every ranger emits: iscd-fast MAE 0.0169 m, "
    "the jitter floor 0.0168 m (an unbiased estimator cannot do better), the dissertation method 0.0166 "
    "(ratio 1.02): the true disparity at 25 m is a whole 84 px, where the dissertation method's response "
    "to sub-pixel shifts is only 0.87 (pixel locking, tests/test_ranging_estimators.py) and damps the "
    "jitter; at other distances that bias shows (ratios 0.56-0.9)")}


@pytest.mark.slow
@pytest.mark.parametrize("distance_m", xfail_where([30.0, 60.0], SLOW_MAE))
def test_project_method_per_frame_mae_target_5000_frames(distance_m: float) -> None:
    res = _point(distance_m, 5000)
    s = res.stats(res.project_method)
    assert s.failed == 0 and s.n >= 4000
    assert s.mae <= TARGET_M[distance_m]


@pytest.mark.slow
@pytest.mark.parametrize("distance_m", xfail_where(list(RANGING_DISTANCES_M), SLOW_PEERS))
def test_project_method_below_every_peer_5000_frames(distance_m: float) -> None:
    """Every distance, 5000 frames, on the frames every ranger emits (on every scored frame
    too, two frames of the dimmest level that the gate rejects for every method give
    iscd-fast 1.6-1.9 m errors at 25 m; no user ever sees those ranges)."""
    res = _point(distance_m, 5000)
    ratios = _ratios(res)
    assert all(r < 1.0 for r in ratios.values()), ratios
