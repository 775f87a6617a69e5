"""The compiled per-frame kernels against their numpy references, on rendered frames.

Tolerances (float64 kernels against references that sum partly in float32):
LED positions 1e-4 px, luminance 1e-5 relative, light maps 1e-4 DN, tracking fits 1e-9
(the same arithmetic), ranging profiles 1e-5 relative and disparities 1e-5 px.
"""

from __future__ import annotations

import numpy as np
import pytest

from fakes import render_pairs
from iscd.core.config import default_config
from iscd.decode.tracking.detect import GridFit, detect_array, light_map, track_on_light
from iscd.decode.tracking.follow_kernel import follow_and_measure_compiled
from iscd.decode.tracking.luminance import follow_and_measure, grid_sample
from iscd.decode.tracking.track_kernel import LightAccumulator, track_on_light_compiled




@pytest.fixture(scope="module")
def fits(rendered_default):
    L, R = rendered_default
    fl = detect_array(L[:64], 8, 8)
    fr = detect_array(R[:64], 8, 8)
    assert fl is not None and fr is not None
    return fl, fr


def _compare_follow(frames, starts, box, sigmas, **kw):
    i1, i2 = {}, {}
    (a_l, a_r), (la, ra) = follow_and_measure(frames, starts, box, sigmas, info=i1, **kw)
    (b_l, b_r), (lb, rb) = follow_and_measure_compiled(frames, starts, box, sigmas, info=i2, **kw)
    for a, b in ((a_l, b_l), (a_r, b_r)):
        assert np.abs(a - b).max() < 1e-4
    for a, b in ((la, lb), (ra, rb)):
        assert np.all(np.abs(a - b) <= 1e-5 * np.maximum(np.abs(a), 1.0))
    np.testing.assert_allclose(i1["light"], i2["light"], rtol=1e-6)
    return b_l


@pytest.mark.parametrize("block", [slice(64, 80), slice(130, 146), slice(200, 232)])
def test_following_and_luminance_match_the_reference(rendered_default, fits, block) -> None:
    L, R = rendered_default
    fl, fr = fits
    rng = np.random.default_rng(block.start)
    # start a fraction of a pixel off, so that the following has work to do
    starts = [fl.centers + rng.normal(0, 0.4, 2), fr.centers + rng.normal(0, 0.4, 2)]
    c = _compare_follow([L[block], R[block]], starts, 5, [1.4, 1.3], use=grid_sample(8, 8))
    assert np.abs(c - fl.centers).max() < 1.5  # and it followed somewhere sensible


def test_following_with_per_frame_starts_and_remembered_light(rendered_default, fits) -> None:
    """(F, N, 2) starts that differ frame by frame (the background is then each patch's
    least pixel) and a remembered lit light."""
    L, R = rendered_default
    fl, fr = fits
    F = 16
    drift = np.linspace(0, 1.2, F)[:, None, None] * np.array([1.0, -0.5])
    starts = [fl.centers[None] + drift, fr.centers[None] + drift]
    _compare_follow([L[96:112], R[96:112]], starts, 3, [0.9, 0.9], lit_light=np.array([9000.0, 4000.0]))
    # all LEDs steer, no scale, no acceleration
    _compare_follow([L[96:112], R[96:112]], starts, 5, [1.2, 1.2], iterations=2)


def test_following_near_the_image_edge() -> None:
    """Patches that would cross the image edge are moved inside it, in both."""
    rng = np.random.default_rng(3)
    fr = rng.integers(0, 60, (8, 40, 40)).astype(np.uint8)
    fr[:, 1:4, 1:4] += 150
    starts = [np.array([[2.0, 2.0], [37.5, 20.0]]), np.array([[2.2, 1.8], [38.0, 21.0]])]
    _compare_follow([fr, fr[::-1].copy()], starts, 3, [1.0, 1.0])


def test_sixteen_bit_frames(rendered_default, fits) -> None:
    L, R = rendered_default
    fl, fr = fits
    L16 = L[64:80].astype(np.uint16) * 16
    R16 = R[64:80].astype(np.uint16) * 16
    _compare_follow([L16, R16], [fl.centers, fr.centers], 5, [1.4, 1.3], use=grid_sample(8, 8))


def test_light_map_folded_block_by_block_equals_the_reference(rendered_default, fits) -> None:
    L, _ = rendered_default
    fl, _ = fits
    x0, y0, x1, y1 = fl.bbox(2 * fl.pitch_px + 4)
    acc = LightAccumulator((x0, y0, x1, y1))
    for s in range(64, 128, 16):
        acc.add(L[s:s + 16])
    ref = light_map(L[64:128, y0:y1, x0:x1])
    assert acc.frames == 64
    assert np.abs(acc.light_map() - ref).max() < 1e-4


def test_grid_tracking_matches_the_reference(rendered_default, fits) -> None:
    L, _ = rendered_default
    fl, _ = fits
    x0, y0, x1, y1 = fl.bbox(2 * fl.pitch_px + 4)
    light = light_map(L[64:96, y0:y1, x0:x1])
    rng = np.random.default_rng(1)
    for _ in range(10):
        prev = GridFit(origin=(fl.origin[0] - x0 + rng.normal(0, 0.5), fl.origin[1] - y0 + rng.normal(0, 0.5)),
                       pitch_px=fl.pitch_px * rng.uniform(0.97, 1.03), rows=8, cols=8, score=fl.score,
                       spot_px=fl.spot_px)
        a = track_on_light(light, prev, 0, 0)
        b = track_on_light_compiled(light, prev, 0, 0)
        assert abs(a.origin[0] - b.origin[0]) < 1e-9 and abs(a.origin[1] - b.origin[1]) < 1e-9
        assert abs(a.pitch_px - b.pitch_px) < 1e-9 and abs(a.score - b.score) < 1e-9 * max(1.0, a.score)


def test_ranging_projection_matches_the_reference(rendered_default) -> None:
    from iscd.decode.ranging.project_kernel import patch_minimum, project_patches
    from iscd.decode.ranging.projected import ring_indices, robust_level

    L, _ = rendered_default
    fr = L[64:80]
    rng = np.random.default_rng(5)
    # inside, and crossing the top-left and the bottom-right image edges
    for x0, y0, h, w in ((200, 210, 60, 80), (-6, -4, 30, 40), (490, 495, 30, 40)):
        pad = np.zeros((16, h, w), np.float32)
        ya, yb, xa, xb = max(0, y0), min(512, y0 + h), max(0, x0), min(512, x0 + w)
        pad[:, ya - y0:yb - y0, xa - x0:xb - x0] = fr[:, ya:yb, xa:xb]
        bg = patch_minimum(fr, x0, y0, h, w)
        np.testing.assert_array_equal(bg, pad.min(axis=0))
        ring = ring_indices(h, w)
        snr_w = rng.random(h * w)
        row_w = rng.random(h)
        ped, mad, sig, prof = project_patches(fr, x0, y0, bg, ring, snr_w, row_w)
        rp, rm = robust_level(pad.reshape(16, -1)[:, ring] - bg.ravel()[ring], spread=True)
        np.testing.assert_array_equal(ped, rp)
        np.testing.assert_allclose(mad, rm, rtol=1e-6)  # the reference multiplies in float32
        res = pad - bg - ped[:, None, None]
        np.testing.assert_allclose(sig, res.reshape(16, -1) @ snr_w, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(prof, np.einsum("h,nhw->nw", row_w, res), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("scene", ["default", "pwm16_50m"])
def test_the_decoder_gives_the_same_records_compiled_or_not(scene, rendered_default) -> None:
    from iscd.decode.stream import StreamDecoder
    from iscd.sim.presets import override

    cfg = default_config()
    if scene == "default":
        L, R = rendered_default
    else:
        cfg = override(cfg, transmitter={"levels": 16}, scene={"distance_m": 50.0})
        L, R = render_pairs(cfg, 192)
    ids = np.arange(L.shape[0])
    out = {}
    for compiled in (False, True):
        dec = StreamDecoder(cfg, compiled=compiled)
        recs = []
        for s in range(0, L.shape[0], 16):
            recs += dec.push(ids[s:s + 16], ids[s:s + 16] / 1000.0, L[s:s + 16], R[s:s + 16])
        out[compiled] = ({r["frame"]: r for r in recs if r["type"] == "range"}, dec.last_centres, dec.last_luminance)
    (ra, ca, la), (rb, cb, lb) = out[False], out[True]
    assert ra and set(ra) == set(rb)
    assert max(abs(ra[f]["disparity_px"] - rb[f]["disparity_px"]) for f in ra) < 1e-5
    assert np.abs(ca[0] - cb[0]).max() < 1e-4 and np.abs(ca[1] - cb[1]).max() < 1e-4
    assert np.all(np.abs(la[2] - lb[2]) <= 1e-5 * np.maximum(np.abs(la[2]), 1.0))


@pytest.mark.parametrize("w", [40, 63, 80])
def test_correlation_peak_matches_the_reference(w: int) -> None:
    from iscd.decode.ranging.project_kernel import correlate_1d_compiled
    from iscd.decode.ranging.projected import correlate_1d

    rng = np.random.default_rng(w)
    x = np.arange(w)
    base = np.exp(-0.5 * ((x - w / 2) / 2.0) ** 2) * 100
    shifts = rng.uniform(-3, 3, 16)
    left = np.stack([np.interp(x, x + s, base) for s in shifts]) + rng.normal(0, 1, (16, w))
    right = base + rng.normal(0, 1, (16, w))
    for ms in (None, 3.5):
        for beta in (0.0, 0.5, 1.0):
            a = correlate_1d(left, right, beta=beta, max_shift_px=ms)
            b = correlate_1d_compiled(left, right, beta=beta, max_shift_px=ms)
            assert np.abs(a.dx - b.dx).max() < 1e-9
            assert np.abs(a.height - b.height).max() < 1e-9
            assert np.allclose(a.sigma, b.sigma, rtol=1e-7, equal_nan=True)
    assert np.abs(b.dx - shifts).max() < 0.3  # and it found the shifts (left - right, px)


def test_the_live_path_compiles_nothing_after_the_warm_up(rendered_default) -> None:
    """After iscd.core.jit.warm_up() (what the daemon runs before the cameras start) decoding the
    default scene as the daemon does -- writable block buffers, ranging every frame --
    compiles no kernel again (a compile mid-stream stalls the frame loop for seconds on
    the first start after an install)."""
    from iscd.core import jit
    from iscd.decode.stream import StreamDecoder

    L, R = rendered_default
    dec = StreamDecoder(default_config())
    jit.warm_up()
    before = jit.signatures()
    ids = np.arange(L.shape[0])
    bl = np.empty((16,) + L.shape[1:], L.dtype)
    br = np.empty_like(bl)
    for s in range(0, L.shape[0], 16):
        bl[:] = L[s:s + 16]
        br[:] = R[s:s + 16]
        dec.push(ids[s:s + 16], ids[s:s + 16] / 1000.0, bl, br)
    assert dec.track is not None
    after = jit.signatures()
    assert {k: v for k, v in after.items() if v != before.get(k)} == {}


def test_frames_smaller_than_a_patch_take_the_reference_path() -> None:
    """A camera ROI smaller than the following patch: the compiled entry point gives the
    reference's result (edge pixels repeated) instead of failing."""
    rng = np.random.default_rng(9)
    fr = rng.integers(0, 200, (6, 9, 9)).astype(np.uint8)
    starts = [np.array([[4.0, 4.0]]), np.array([[4.2, 3.9]])]
    (a, _), (la, _) = follow_and_measure([fr, fr], starts, 5, [1.5, 1.5])
    (b, _), (lb, _) = follow_and_measure_compiled([fr, fr], starts, 5, [1.5, 1.5])
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(la, lb)


def test_block_ranging_in_one_call_matches_the_reference(rendered_default, fits) -> None:
    """StereoRanger's compiled path (block_minima + range_block: projections, noise, SNR,
    correlation and range in one call) against its numpy reference on rendered blocks,
    the running background carried over five blocks: disparities 1e-5 px (measured 1.4e-7),
    ranges 1e-6 relative, their sigma 1e-4 relative (a residual-phase variance: measured
    1.2e-6),
    correlation quality 1e-6 (the reference sums partly in float32: measured 3.5e-8), the
    same valid frames, SNR 1e-6 relative."""
    from iscd.decode.ranging.project_kernel import block_minima
    from iscd.decode.ranging.stereo import StereoRanger

    L, R = rendered_default
    fl, fr = fits
    from iscd.calibration.io import StereoCalibration

    cal = StereoCalibration.ideal(default_config().camera)
    a, b = StereoRanger(cal, compiled=False), StereoRanger(cal, compiled=True)
    for s in range(64, 144, 16):
        ra = a.measure(L[s:s + 16], R[s:s + 16], fl, fr)
        rb = b.measure(L[s:s + 16], R[s:s + 16], fl, fr)
        np.testing.assert_array_equal(ra.valid, rb.valid)
        assert ra.valid.any()
        np.testing.assert_allclose(ra.disparity_px, rb.disparity_px, rtol=0, atol=1e-5)  # measured 1.4e-7
        np.testing.assert_allclose(ra.z_m, rb.z_m, rtol=1e-6, atol=0, equal_nan=True)
        np.testing.assert_allclose(ra.sigma_m, rb.sigma_m, rtol=1e-4, equal_nan=True)  # measured 1.2e-6
        np.testing.assert_allclose(ra.snr, rb.snr, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(ra.quality, rb.quality, rtol=0, atol=1e-6)  # measured 3.5e-8
    # both patches' minima in one call, also across the image edge (0 outside)
    for x0l, x0r, y0 in ((200, 170, 210), (-5, 480, -3)):
        ml, mr = block_minima(L[64:80], R[64:80], x0l, x0r, y0, 40, 50)
        for m, fr_, x0 in ((ml, L[64:80], x0l), (mr, R[64:80], x0r)):
            pad = np.zeros((16, 40, 50), np.float32)
            ya, yb, xa, xb = max(0, y0), min(512, y0 + 40), max(0, x0), min(512, x0 + 50)
            pad[:, ya - y0:yb - y0, xa - x0:xb - x0] = fr_[:, ya:yb, xa:xb]
            np.testing.assert_array_equal(m, pad.min(axis=0))


def test_deferred_block_tail_gives_the_same_records(rendered_default) -> None:
    """push(defer=True) + finish_block() (the daemon: ranges out before the demodulation
    hand-off and the tracking update) gives exactly the records of push() (as a set; the
    packets come out of finish_block), the same tracking and the same luminance."""
    from iscd.decode.stream import StreamDecoder

    L, R = rendered_default
    ids = np.arange(L.shape[0])
    out = {}
    for defer in (False, True):
        dec = StreamDecoder(default_config())
        recs = []
        for s in range(0, L.shape[0], 16):
            recs += dec.push(ids[s:s + 16], ids[s:s + 16] / 1000.0, L[s:s + 16], R[s:s + 16], defer=defer)
            if defer:
                recs += dec.finish_block()
        recs += dec.finish()
        out[defer] = (sorted(repr(r) for r in recs), dec.track, dec.last_luminance[2], dec.counters)
    (ra, ta, la, ca), (rb, tb, lb, cb) = out[False], out[True]
    assert ra == rb and any("'range'" in r for r in ra)
    assert ta == tb and ca == cb
    np.testing.assert_array_equal(la, lb)


def test_light_map_median_is_numpys_exactly() -> None:
    """The smoothing's median (a radix selection on the float32 bits) is np.median's value
    bit for bit: odd and even counts, ties, signed zeros, subnormals, infinities, negative
    values (NaN, which a light map has not, goes to Numba's np.median as before)."""
    from iscd.decode.tracking.track_kernel import _median_f32

    rng = np.random.default_rng(11)
    for trial in range(600):
        n = int(rng.integers(1, 400)) if trial % 2 else int(rng.integers(1, 9000))
        kind = trial % 5
        if kind == 0:
            x = rng.normal(0, 10, n)
        elif kind == 1:
            x = rng.integers(-3, 4, n) / 4
        elif kind == 2:
            x = rng.integers(0, 5, n) * 1.0
        elif kind == 3:
            x = rng.choice([0.0, -0.0, 1e-40, -1e-40, np.inf, -np.inf, 3.0], n)
        else:
            x = rng.exponential(1, n) * 10.0 ** rng.integers(-30, 30, n)
        x = x.astype(np.float32)
        ref = np.median(x.astype(np.float64))
        assert _median_f32(x) == ref, trial


@pytest.mark.parametrize("sigma", [0.7, 0.4, 1.3])
def test_light_smoothing_is_scipys_arithmetic(rendered_default, fits, sigma: float) -> None:
    """The compiled smoothing (median removed, Gaussian filter) against scipy's
    gaussian_filter on the same map: seven taps (the tracking's) and other sizes."""
    from scipy.ndimage import gaussian_filter

    from iscd.decode.tracking.track_kernel import _smooth_light

    L, _ = rendered_default
    fl, _ = fits
    x0, y0, x1, y1 = fl.bbox(2 * fl.pitch_px + 4)
    light = light_map(L[64:96, y0:y1, x0:x1]).astype(np.float32)
    out = np.empty(light.shape)
    assert _smooth_light(np.ascontiguousarray(light), sigma, out)
    act = np.maximum(light.astype(np.float64) - np.median(light.astype(np.float64)), 0.0)
    np.testing.assert_allclose(out, gaussian_filter(act, sigma), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int8, np.int16])
def test_light_fold_in_narrow_sums_is_exact(dtype) -> None:
    """The fold's partial sums in narrow integers (16 bits for 8-bit frames, 257 frames at a
    time) give numpy's int64 sums and minima exactly, at the extremes of the type and across
    a chunk boundary."""
    from iscd.decode.tracking.track_kernel import LightAccumulator

    info = np.iinfo(dtype)
    rng = np.random.default_rng(3)
    n = 300 if np.dtype(dtype).itemsize == 1 else 40
    fr = rng.integers(info.min, int(info.max) + 1, (n, 12, 15)).astype(dtype)
    fr[:, 2, 3] = info.max
    fr[:, 4, 5] = info.min
    acc = LightAccumulator((2, 1, 13, 11))
    acc.add(fr[:7])
    acc.add(fr[7:])
    win = fr[:, 1:11, 2:13]
    np.testing.assert_array_equal(acc._sum, win.astype(np.int64).sum(axis=0))
    np.testing.assert_array_equal(acc._min, win.min(axis=0))
    ref = (win.astype(np.int64).sum(axis=0) / n - win.min(axis=0)).astype(np.float32)
    np.testing.assert_array_equal(acc.light_map(), ref)


def test_ring_medians_by_counting_equal_numpys() -> None:
    """The ring's pedestal and MAD (counted when the residuals are integers of a small span,
    np.median otherwise: a background that is not integers, a wide span of 16-bit values)
    are robust_level's exactly."""
    from iscd.decode.ranging.project_kernel import project_patches
    from iscd.decode.ranging.projected import ring_indices, robust_level

    rng = np.random.default_rng(8)
    h, w = 20, 24
    ring = ring_indices(h, w)
    for dtype, hi, frac in ((np.uint8, 6, False), (np.uint8, 250, False), (np.uint16, 60000, False),
                            (np.uint8, 6, True), (np.uint16, 4000, True)):
        fr = rng.integers(0, hi, (9, 40, 40)).astype(dtype)
        bg = rng.integers(0, 3, (h, w)).astype(np.float32) + (0.25 if frac else 0.0)
        ped, mad, _, _ = project_patches(fr, 7, 5, bg, ring, rng.random(h * w), rng.random(h))
        res = fr[:, 5:5 + h, 7:7 + w].reshape(9, -1)[:, ring].astype(np.float64) - bg.ravel()[ring]
        rp, rm = robust_level(res.astype(np.float32), spread=True)
        np.testing.assert_array_equal(ped, rp)
        np.testing.assert_allclose(mad, rm, rtol=1e-6)
        for f in range(9):  # exact against float64 medians
            p = np.median(res[f])
            assert ped[f] == p and mad[f] == 1.4826 * np.median(np.abs(res[f] - p))


def test_block_ranging_follows_a_moving_patch(rendered_default, fits) -> None:
    """The live one-call ranging (block minima and the running background inside the kernel)
    equals the reference while the patch moves by whole pixels between blocks (the held
    backgrounds overlap it only in part) and with read-only and 16-bit frames."""
    from dataclasses import replace

    from iscd.calibration.io import StereoCalibration
    from iscd.decode.ranging.stereo import StereoRanger

    L, R = rendered_default
    fl, fr = fits
    cal = StereoCalibration.ideal(default_config().camera)
    for frames in ("u8", "readonly", "u16"):
        a, b = StereoRanger(cal, compiled=False), StereoRanger(cal, compiled=True)
        for i, s in enumerate(range(64, 160, 16)):
            dx = (0, 1, 3, 3, -2, 0)[i]
            gl, gr = (replace(g, origin=(g.origin[0] + dx, g.origin[1] - dx / 2)) for g in (fl, fr))
            bl, br = L[s:s + 16], R[s:s + 16]
            if frames == "readonly":
                bl, br = bl.copy(), br.copy()
                bl.setflags(write=False)
                br.setflags(write=False)
            elif frames == "u16":
                bl, br = bl.astype(np.uint16) * 16, br.astype(np.uint16) * 16
            ra, rb = a.measure(bl, br, gl, gr), b.measure(bl, br, gl, gr)
            np.testing.assert_array_equal(ra.valid, rb.valid)
            np.testing.assert_allclose(ra.disparity_px, rb.disparity_px, rtol=0, atol=1e-5)
            np.testing.assert_allclose(ra.z_m, rb.z_m, rtol=1e-6, atol=0, equal_nan=True)
            np.testing.assert_allclose(ra.snr, rb.snr, rtol=1e-6, atol=1e-6)


def test_live_ranging_equals_the_block_kernels_across_the_image_edges(rendered_default, fits) -> None:
    """StereoRanger's one-call live path (block minima in the projection pass, the running
    background in the kernel) gives block_minima + RunningMinimum.update_min + range_block's
    numbers with the patches cut across each image edge (pixels outside count as 0)."""
    from dataclasses import replace

    from iscd.calibration.io import StereoCalibration
    from iscd.decode.ranging.project_kernel import block_minima, range_block
    from iscd.decode.ranging.stereo import _QUANT_NOISE_DN, RunningMinimum, StereoRanger

    L, R = rendered_default
    fl, fr = fits
    cal = StereoCalibration.ideal(default_config().camera)
    for shift in ((-240, 0), (260, 0), (0, -245), (0, 250)):
        live = StereoRanger(cal, compiled=True)
        gl, gr = (replace(g, origin=(g.origin[0] + shift[0], g.origin[1] + shift[1])) for g in (fl, fr))
        x0l, y0, x0r, w, h = live.patch_geometry(gl, gr)
        assert min(x0l, x0r, y0) < 0 or max(x0l, x0r) + w > 512 or y0 + h > 512
        back = RunningMinimum(live.settings.background_frames), RunningMinimum(live.settings.background_frames)
        for s in range(64, 128, 16):
            bl = np.ascontiguousarray(np.roll(L[s:s + 16], shift, axis=(2, 1)))
            br = np.ascontiguousarray(np.roll(R[s:s + 16], shift, axis=(2, 1)))
            got = live.measure(bl, br, gl, gr)
            g = live._geometry(gl, gr)
            est = live._estimator_for(gl.pitch_px, live.saturation_level(bl))
            assert g.plan is not None
            cl, cr = block_minima(bl, br, x0l, x0r, y0, h, w)
            z, d, sig, q, valid, snr = range_block(
                bl, br, x0l, x0r, y0, back[0].update_min(cl, x0l, y0, 16), back[1].update_min(cr, x0r, y0, 16),
                g.ring, g.snr_left, g.snr_right, g.plan.weights_left, g.plan.weights_right, beta=est.beta,
                band_cutoff=est.band_cutoff, max_shift_px=g.plan.max_shift_px, iterations=est.iterations,
                sigma_floor_px=est.sigma_floor_px, focal_px=live.f_px, baseline_m=live.b_m,
                quant_noise_dn=_QUANT_NOISE_DN, min_snr=live.settings.min_snr, min_quality=live.min_quality)
            np.testing.assert_array_equal(got.valid, valid)
            for a, b in ((got.z_m, z), (got.disparity_px, d), (got.sigma_m, sig), (got.quality, q), (got.snr, snr)):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12, equal_nan=True)
