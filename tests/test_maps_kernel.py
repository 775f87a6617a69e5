"""The detection's per-pixel maps in one compiled pass against numpy (identical values)."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.decode.tracking.detect import activity_map, detect_array, detect_auto, lit_map
from iscd.decode.tracking.maps_kernel import look_maps, look_maps_reference


@pytest.mark.parametrize("start, n", [(0, 64), (100, 2), (37, 17)])
def test_maps_equal_numpy_on_rendered_frames(rendered_default, start, n) -> None:
    L, R = rendered_default
    for frames in (L[start:start + n], R[start:start + n]):
        got = look_maps(frames)
        ref = look_maps_reference(frames)
        for g, r in zip(got, ref):
            assert g.dtype == r.dtype and g.shape == r.shape
            np.testing.assert_array_equal(g, r)
        # and the detection's own functions
        np.testing.assert_array_equal(got[0], activity_map(frames))
        np.testing.assert_array_equal(got[3].astype(np.float32) - got[2].astype(np.float32), lit_map(frames))


def test_sixteen_bit_frames_and_the_exactness_limit() -> None:
    rng = np.random.default_rng(5)
    f = rng.integers(0, 4096, (40, 33, 70), dtype=np.uint16)
    for g, r in zip(look_maps(f), look_maps_reference(f)):
        np.testing.assert_array_equal(g, r)
    # 300 frames of full-scale 16-bit data: float32 sums would round, so numpy's path is taken
    big = rng.integers(60000, 65536, (300, 4, 5), dtype=np.uint16)
    for g, r in zip(look_maps(big), look_maps_reference(big)):
        np.testing.assert_array_equal(g, r)


def test_non_contiguous_and_bad_shapes() -> None:
    rng = np.random.default_rng(6)
    f = rng.integers(0, 256, (10, 40, 60), dtype=np.uint8)[:, 5:30, ::2]
    for g, r in zip(look_maps(f), look_maps_reference(f)):
        np.testing.assert_array_equal(g, r)
    with pytest.raises(ValueError, match="n >= 2"):
        look_maps(f[:1])
    with pytest.raises(ValueError, match="n >= 2"):
        look_maps(f[0])


def test_detection_finds_the_same_grid(rendered_default) -> None:
    """detect_array / detect_auto on the compiled maps: the default scene's 8x8 where it is."""
    L, _ = rendered_default
    fa = detect_array(L[:64], 8, 8)
    fb = detect_auto(L[:64])
    assert fa is not None and fb is not None
    assert (fb.rows, fb.cols) == (8, 8)
    np.testing.assert_allclose(fa.center, fb.center, atol=0.5)
