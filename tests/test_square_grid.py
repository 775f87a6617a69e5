"""An array's carried LED centres put back on a square grid at every block
(:func:`iscd.decode.tracking.detect.square_grid`, compiled
:func:`iscd.decode.tracking.track_kernel.square_grid_compiled`): the grid of a known origin and
pitch comes back exactly, noise is least-squares averaged, the two agree, and following a
closing 8x8 array (randomized physics) no longer lets its edge columns drift off."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.decode.tracking.detect import GridFit, square_grid
from iscd.decode.tracking.track_kernel import square_grid_compiled


@pytest.mark.parametrize("rows,cols", [(8, 8), (4, 8), (8, 4), (2, 16), (1, 3)])
def test_a_grid_comes_back_exactly(rows: int, cols: int) -> None:
    fit = GridFit((101.37, 57.9), 6.23, rows, cols, score=1.0)
    for f in (square_grid, square_grid_compiled):
        np.testing.assert_allclose(f(np.array(fit.centers), rows, cols), fit.centers, atol=1e-9)


def test_least_squares_and_compiled_agree() -> None:
    rng = np.random.default_rng(4)
    fit = GridFit((80.0, 40.0), 5.0, 8, 8, score=1.0)
    noisy = fit.centers + rng.normal(0.0, 0.3, fit.centers.shape)
    got = square_grid(noisy, 8, 8)
    np.testing.assert_allclose(square_grid_compiled(noisy, 8, 8), got, atol=1e-9)
    # a square grid: one pitch along x and y, and the residual is orthogonal to the model
    px = np.diff(got.reshape(8, 8, 2)[:, :, 0], axis=1)
    py = np.diff(got.reshape(8, 8, 2)[:, :, 1], axis=0)
    assert np.ptp(px) < 1e-9 and np.ptp(py) < 1e-9 and abs(px[0, 0] - py[0, 0]) < 1e-9
    assert abs(px[0, 0] - 5.0) < 0.05 and np.hypot(*(got.mean(0) - fit.centers.mean(0))) < 0.1
    # distorted: x stretched, y squeezed by 2 %: the fitted pitch is between them
    c = fit.centers.copy()
    m = c.mean(0)
    c[:, 0] = m[0] + 1.02 * (c[:, 0] - m[0])
    c[:, 1] = m[1] + 0.98 * (c[:, 1] - m[1])
    p = np.diff(square_grid(c, 8, 8)[:2, 0])[0]
    assert 4.95 < p < 5.05


def test_closing_array_keeps_its_edges() -> None:
    """8x8 HDR closing at 40 km/h from 32 m to 25 m (randomized physics, seed 1003: texture
    at 74 DN, a 0.2 m lateral offset drifting, 0.3 px vibration): after the approach the
    followed LEDs of the edge columns and rows stay within 0.25 px of the truth (they had
    drifted 0.4 px off here, and 1-1.6 px over the approach from 50 m, before the grid
    was put back square at every block)."""
    from iscd.core.config import default_config
    from iscd.decode.stream import StreamDecoder
    from iscd.eval.oracle import _decoder_cfg, true_centres
    from iscd.eval.suites import MotionCase, motion_cfg
    from iscd.eval.sweeps import ReceiverMode
    from iscd.sim.scene import Scene

    case = MotionCase("8x8-close", 64, 40.0, 32.0, 25.0, 0.3)
    cfg, _ = motion_cfg(default_config(), case, 1003, scene={"background_motion": "whole"}, randomize=True)
    scene = Scene(cfg)
    n = 940
    truth = scene.truth(np.arange(n))
    dec = StreamDecoder(_decoder_cfg(cfg, ReceiverMode("both", "both")))
    B = 32
    Lb = np.empty((B, scene.height, scene.width), np.uint8)
    Rb = np.empty_like(Lb)
    got = np.full((2, n, 64, 2), np.nan)
    try:
        for a in range(0, n, B):
            ids = np.arange(a, min(n, a + B))
            for i, k in enumerate(ids):
                scene.render_pair_into(int(k), Lb[i], Rb[i])
            dec.push(ids, ids / scene.fps, Lb[:ids.size], Rb[:ids.size])
            if dec.track is not None and dec.last_centres is not None and dec.last_centres[0].shape[0] == ids.size:
                for c in (0, 1):
                    got[c, ids] = dec.last_centres[c]
    finally:
        dec.close()
    for c in (0, 1):
        err = (got[c, -300:] - true_centres(truth, c)[-300:]).reshape(300, 8, 8, 2)
        edges = np.concatenate([err[:, :, 0, 0], err[:, :, 7, 0], err[:, 0, :, 1], err[:, 7, :, 1]], axis=1)
        med = np.nanmedian(edges, axis=0)  # each edge LED's typical error over the last 0.3 s
        assert np.isfinite(med).all()
        assert np.abs(med).max() < 0.25, f"camera {c}: an edge LED {np.abs(med).max():.2f} px off"
