"""Compiled per-frame kernels of the scene renderer, each with its pure-numpy reference.

The scene renders a frame as: copy a noisy background frame from the bank (:func:`copy_frame`),
then for each window around the LEDs (and flickering distractors) add the light of every
source set (:func:`add_sources`: the spot cores from their cached footprints and the
separable glare) into a float64 canvas and read it out through the sensor
(:func:`expose_window`: background, PRNU, shot and read noise, dark level, rounding,
clipping); with blooming (``sensor.blooming`` > 0) the window's canvas first goes through
:func:`bloom_columns` (charge above full well spilled along the columns). The references
(``*_ref``) do the same with the numpy functions of
:mod:`iscd.sim.optics` and :mod:`iscd.sim.sensor` (``Scene(..., compiled=False)`` renders
with them); ``tests/test_sim_kernels.py`` checks that both agree.

Agreement: the cores are summed in the same order and precision as ``np.bincount`` (float64
sums of float32 products), the sensor arithmetic is the same float32 sequence as
:meth:`~iscd.sim.sensor.SensorModel.expose`, and the Gaussian draws are the same
``cv2.randn`` stream (the caller draws them); only the glare's matrix products may round
differently (float64, ~1e-16 relative). So frames agree to the last bit except where a
pixel's signal lies within ~1e-12 DN of a rounding boundary (never seen in the tests).

Units: px, DN (grey levels). All kernels are ``iscd.core.jit.njit`` (cached, nogil) and
registered for :func:`iscd.core.jit.warm_up`; :func:`warm` compiles (or loads) just these.
"""

from __future__ import annotations

import numpy as np

from iscd.core.jit import njit

# ---------------------------------------------------------------- warm-up arguments


def _warm_copy() -> tuple:
    return (np.empty((4, 4), np.uint8), np.zeros((6, 6), np.uint8), 1, 1)


def _warm_sources() -> tuple:
    acc = np.zeros((8, 8))
    kern = np.ones((2, 3, 3), np.float32)
    ij = np.array([1, 4], np.int64)
    return (acc, True, kern, ij, ij, np.ones(2), 1.0, 0.5, 0.1,
            np.ones((8, 1)), np.ones((2, 8)), 2)


def _warm_window() -> tuple:
    o, Y0, X0, acc, ay, ax, bg, prnu, by, bx, z, noise, sensor = _warm_expose()
    _, clear, kern, ix, iy, w, c_amp, c_core, c_flux, gy, gxt, grid_q = _warm_sources()
    return (o, Y0, X0, np.zeros((8, 8)), ay, ax, clear, kern, ix, iy, w, c_amp, c_core, c_flux,
            gy, gxt, grid_q, bg, prnu, by, bx, z, noise, sensor)


def _warm_expose() -> tuple:
    f32 = np.float32
    z = np.zeros((2, 2), np.float32)
    return (np.zeros((4, 4), np.uint8), 1, 1, np.zeros((4, 4)), 0, 0,
            np.ones((6, 6), f32), np.ones((6, 6), f32), 1, 1, z, True,
            np.array([0.01, 0.06, 2.5, 255.499], f32))


# ---------------------------------------------------------------- background copy


@njit(warm=_warm_copy)
def copy_frame(out: np.ndarray, src: np.ndarray, oy: int, ox: int) -> None:
    """out[:, :] = src[oy:oy + H, ox:ox + W] for (H, W) = out.shape (uint8).

    A plain (vectorized) loop: ``np.copyto`` of a 256 kB frame takes 10-15x longer
    (150 instead of 10 us) when the destination starts 1-31 bytes after the source modulo
    4 kB (glibc's ``rep movsb`` on AMD EPYC), which fresh ``np.empty`` frames often do.
    """
    H, W = out.shape
    for y in range(H):  # row views: indices provably >= 0, so the loop vectorizes
        d = out[y]
        s = src[oy + y, ox:ox + W]
        for x in range(W):
            d[x] = s[x]


def copy_frame_ref(out: np.ndarray, src: np.ndarray, oy: int, ox: int) -> None:
    """Reference of :func:`copy_frame`.

    Parameters
    ----------
    out : ndarray of uint8
        (H, W) destination frame.
    src : ndarray of uint8
        Padded source (bank) frame.
    oy, ox : int
        Origin of the copied region in ``src``, px.
    """
    H, W = out.shape
    np.copyto(out, src[oy:oy + H, ox:ox + W])


# ---------------------------------------------------------------- subpixel background motion


def _warm_residual() -> tuple:
    return (np.zeros((4, 4), np.uint8), np.ones((6, 6), np.float32), np.ones((6, 6), np.float32),
            1, 1, 0.25, -0.25, 255.0)


def bilinear_weights(ry: float, rx: float) -> tuple[int, int, float, float]:
    """Where the background shows through a residual image shift (ry, rx) px: image pixel
    p shows the scene at padded position q - r (q the whole-pixel position), between rows
    q + dy and q + dy + 1 (bilinear weights 1 - fy, fy), columns likewise.

    Parameters
    ----------
    ry, rx : float
        Residual shift (y, x), px, within [-1, 1].

    Returns
    -------
    dy, dx : int
        Offsets of the first row and column, px ({-1, 0} for |r| < 1).
    fy, fx : float
        Weights of the second row and column, 0 <= f < 1.
    """
    ty, tx = -float(ry), -float(rx)
    dy, dx = int(np.floor(ty)), int(np.floor(tx))
    return dy, dx, ty - dy, tx - dx


@njit(warm=_warm_residual)
def add_residual_shift(out: np.ndarray, bg: np.ndarray, prnu: np.ndarray, oy: int, ox: int,
                       ry: float, rx: float, top: float) -> None:
    """Move the whole-pixel background frame in ``out`` (H, W uint8, the bank frame at
    padded origin (oy, ox)) on by the residual (ry, rx) px of the rig's shift: every pixel
    gets the change of its photo-signal, ``prnu[q] (bg(q - r) - bg(q))`` DN (``bg`` the
    padded noise-free background, float32, bilinear between its pixels; indices clamped at
    the padded edge), rounded, clipped to 0 .. ``top``. The bank frame's noise stays as it
    was (its variance that of the whole-pixel signal: the change is small next to it).

    Parameters
    ----------
    out : ndarray of uint8 or uint16
        (H, W) frame, DN, changed in place.
    bg, prnu : ndarray of float32
        (Hp, Wp) padded noise-free background (DN) and PRNU gain.
    oy, ox : int
        Padded origin of image pixel (0, 0), px.
    ry, rx : float
        Residual shift (y, x), px.
    top : float
        Top grey level, DN.
    """
    H, W = out.shape
    Hp, Wp = bg.shape
    ty, tx = -ry, -rx
    dy, dx = int(np.floor(ty)), int(np.floor(tx))
    fy, fx = ty - dy, tx - dx
    w00 = (1.0 - fy) * (1.0 - fx)
    w01 = (1.0 - fy) * fx
    w10 = fy * (1.0 - fx)
    w11 = fy * fx
    # columns whose neighbours need no clamping: [xa, xb) (the rest, at most two, clamped)
    xa = min(max(-(ox + dx), 0), W)
    xb = max(min(Wp - 1 - dx - ox, W), xa)
    for y in range(H):
        q = oy + y
        y0 = min(max(q + dy, 0), Hp - 1)
        y1 = min(max(q + dy + 1, 0), Hp - 1)
        r0 = bg[y0]
        r1 = bg[y1]
        rq = bg[q]
        pq = prnu[q]
        o = out[y]
        for x in range(xa):
            _residual_px(o, x, r0, r1, rq, pq, ox + x, min(max(ox + x + dx, 0), Wp - 1),
                         min(max(ox + x + dx + 1, 0), Wp - 1), w00, w01, w10, w11, top)
        # the interior: row views with indices provably >= 0 (the loop vectorizes)
        a0 = r0[ox + dx + xa:ox + dx + xb]
        a1 = r0[ox + dx + 1 + xa:ox + dx + 1 + xb]
        b0 = r1[ox + dx + xa:ox + dx + xb]
        b1 = r1[ox + dx + 1 + xa:ox + dx + 1 + xb]
        qq = rq[ox + xa:ox + xb]
        pp = pq[ox + xa:ox + xb]
        oo = o[xa:xb]
        for k in range(xb - xa):
            s = w00 * a0[k] + w01 * a1[k] + w10 * b0[k] + w11 * b1[k]
            v = float(oo[k]) + np.floor(pp[k] * (s - qq[k]) + 0.5)
            oo[k] = min(max(v, 0.0), top)  # an integer value: the cast is exact
        for x in range(xb, W):
            _residual_px(o, x, r0, r1, rq, pq, ox + x, min(max(ox + x + dx, 0), Wp - 1),
                         min(max(ox + x + dx + 1, 0), Wp - 1), w00, w01, w10, w11, top)


@njit
def _residual_px(o: np.ndarray, x: int, r0: np.ndarray, r1: np.ndarray, rq: np.ndarray,
                 pq: np.ndarray, c: int, x0: int, x1: int, w00: float, w01: float, w10: float,
                 w11: float, top: float) -> None:
    """One pixel of :func:`add_residual_shift` with its neighbours' columns given."""
    s = w00 * r0[x0] + w01 * r0[x1] + w10 * r1[x0] + w11 * r1[x1]
    v = float(o[x]) + np.floor(pq[c] * (s - rq[c]) + 0.5)
    o[x] = min(max(v, 0.0), top)


def add_residual_shift_ref(out: np.ndarray, bg: np.ndarray, prnu: np.ndarray, oy: int, ox: int,
                           ry: float, rx: float, top: float) -> None:
    """Reference of :func:`add_residual_shift` (numpy, the same arithmetic).

    Parameters
    ----------
    out : ndarray of uint8 or uint16
        (H, W) frame, DN, changed in place.
    bg, prnu : ndarray of float32
        (Hp, Wp) padded noise-free background (DN) and PRNU gain.
    oy, ox : int
        Padded origin of image pixel (0, 0), px.
    ry, rx : float
        Residual shift (y, x), px.
    top : float
        Top grey level, DN.
    """
    H, W = out.shape
    s = _bilinear(bg, oy, ox, H, W, ry, rx)
    q = bg[oy:oy + H, ox:ox + W].astype(np.float64)
    d = np.floor(prnu[oy:oy + H, ox:ox + W].astype(np.float64) * (s - q) + 0.5)
    out[...] = np.clip(out.astype(np.float64) + d, 0.0, top).astype(out.dtype)


def _bilinear(bg: np.ndarray, y: int, x: int, h: int, w: int, ry: float, rx: float) -> np.ndarray:
    """(h, w) float64: the padded background from (y, x) under the residual shift (ry, rx),
    bilinear, indices clamped at the padded edge (:func:`bilinear_weights`)."""
    Hp, Wp = bg.shape
    dy, dx, fy, fx = bilinear_weights(ry, rx)
    ys = np.arange(y, y + h)
    xs = np.arange(x, x + w)
    y0 = np.clip(ys + dy, 0, Hp - 1)[:, None]
    y1 = np.clip(ys + dy + 1, 0, Hp - 1)[:, None]
    x0 = np.clip(xs + dx, 0, Wp - 1)[None, :]
    x1 = np.clip(xs + dx + 1, 0, Wp - 1)[None, :]
    b = bg.astype(np.float64)
    return ((1 - fy) * (1 - fx) * b[y0, x0] + (1 - fy) * fx * b[y0, x1]
            + fy * (1 - fx) * b[y1, x0] + fy * fx * b[y1, x1])


def shifted_window(bg: np.ndarray, y: int, x: int, h: int, w: int, ry: float, rx: float) -> np.ndarray:
    """The noise-free background a render window shows under a residual shift (as
    :func:`add_residual_shift`: bilinear, indices clamped at the padded edge).

    Parameters
    ----------
    bg : ndarray of float32
        (Hp, Wp) padded noise-free background, DN.
    y, x : int
        Padded position of the window's first pixel, px.
    h, w : int
        Window size, px.
    ry, rx : float
        Residual shift (y, x), px.

    Returns
    -------
    ndarray of float32
        (h, w) background, DN.
    """
    return np.ascontiguousarray(_bilinear(bg, y, x, h, w, ry, rx), dtype=np.float32)


# ---------------------------------------------------------------- light of the sources


@njit
def _add_cores(acc: np.ndarray, kern: np.ndarray, ix: np.ndarray, iy: np.ndarray,
               w: np.ndarray, c_amp: float, c_core: float) -> None:
    """acc[window of s] += float32(kern[s] * float32(w[s] c_amp c_core)) for every source
    (the order and precision of ``np.bincount`` over the footprint)."""
    n, k, _ = kern.shape
    for s in range(n):  # (window views: indices provably >= 0, no wrap-around code)
        a32 = np.float32(w[s] * c_amp * c_core)
        win = acc[iy[s]:iy[s] + k, ix[s]:ix[s] + k]
        ks = kern[s]
        for r in range(k):
            for q in range(k):
                win[r, q] += np.float64(ks[r, q] * a32)


@njit
def _glare_t(w: np.ndarray, c_amp: float, c_flux: float, gxt: np.ndarray, grid_q: int,
             m: int) -> np.ndarray:
    """(m, w) flux @ gx^T: the glare of each source row along the canvas columns."""
    W = gxt.shape[1]
    t = np.zeros((m, W))
    for r in range(m):
        tr = t[r]
        if grid_q > 0:
            for c in range(grid_q):
                f = w[r * grid_q + c] * c_amp * c_flux
                gc = gxt[c]
                for x in range(W):
                    tr[x] += f * gc[x]
        else:
            f = w[r] * c_amp * c_flux
            gc = gxt[r]
            for x in range(W):
                tr[x] = f * gc[x]
    return t


@njit
def _glare_row(row: np.ndarray, gy: np.ndarray, y: int, t: np.ndarray) -> None:
    """row[:] = (gy @ t)[y]: the glare of canvas row y (skips the exact zeros of gy beyond
    8.9 sigma, see optics._gauss)."""
    row[:] = 0.0
    for r in range(t.shape[0]):
        g = gy[y, r]
        if g == 0.0:
            continue
        tr = t[r]
        for x in range(row.size):
            row[x] += g * tr[x]


@njit(warm=_warm_sources)
def add_sources(acc: np.ndarray, clear: bool, kern: np.ndarray, ix: np.ndarray,
                iy: np.ndarray, w: np.ndarray, c_amp: float, c_core: float, c_flux: float,
                gy: np.ndarray, gxt: np.ndarray, grid_q: int) -> None:
    """Add n sources of one spot table into the canvas ``acc`` ((h, w) float64, DN).

    clear: set ``acc`` to 0 first. kern: (n, k, k) float32 core profile P of each source's
    window (from :func:`iscd.sim.optics.footprint`); ix, iy: (n,) window origins in canvas
    px. Source s has light L_s = w[s] * c_amp (DN: on-fraction or flicker gain times the
    grey level of a fully-on source), core peak scale float32(L_s * c_core) and glare flux
    L_s * c_flux (DN px^2). gy: (h, m) and gxt: (q, w) unit-area glare Gaussians of the
    source rows and columns (m = 0: no glare); grid_q > 0: the sources form a row-major
    (m, grid_q) grid (an LED array), else m = q = n (one row and column per source).
    """
    if clear:
        acc[:, :] = 0.0
    _add_cores(acc, kern, ix, iy, w, c_amp, c_core)
    m = gy.shape[1]
    if m == 0:
        return
    t = _glare_t(w, c_amp, c_flux, gxt, grid_q, m)
    row = np.empty(acc.shape[1])
    for y in range(acc.shape[0]):  # acc += gy @ t
        _glare_row(row, gy, y, t)
        ay = acc[y]
        for x in range(row.size):
            ay[x] += row[x]


def add_sources_ref(acc: np.ndarray, clear: bool, kern: np.ndarray, ix: np.ndarray,
                    iy: np.ndarray, w: np.ndarray, c_amp: float, c_core: float,
                    c_flux: float, gy: np.ndarray, gxt: np.ndarray, grid_q: int) -> None:
    """Reference of :func:`add_sources` (``np.bincount`` and matrix products, as
    :func:`iscd.sim.optics.render`).

    Parameters
    ----------
    acc : ndarray of float64
        (hc, wc) light canvas, DN (modified in place).
    clear : bool
        Set ``acc`` to 0 first.
    kern : ndarray of float32
        (n, k, k) core profile P of each source's window.
    ix, iy : ndarray of int64
        (n,) window origins, canvas px.
    w : ndarray of float64
        (n,) on-fraction (0..1) or flicker gain (0..2) of each source.
    c_amp : float
        Grey level of a fully-on source, DN.
    c_core : float
        Core peak scale per DN of light.
    c_flux : float
        Glare flux per DN of light, px^2.
    gy : ndarray of float64
        (hc, m) unit-area glare Gaussians of the source rows, 1/px (m = 0: no glare).
    gxt : ndarray of float64
        (q, wc) unit-area glare Gaussians of the source columns, 1/px.
    grid_q : int
        Columns of the row-major (m, grid_q) source grid; 0: m = q = n.
    """
    n, k, _ = kern.shape
    H, W = acc.shape
    amp = w * c_amp
    core = (amp * c_core).astype(np.float32)
    off = (np.arange(k)[:, None] * W + np.arange(k)[None, :]).ravel()
    flat = ((iy * W + ix)[:, None] + off[None, :]).ravel()
    light = np.bincount(flat, (kern.reshape(n, k * k) * core[:, None]).ravel(),
                        minlength=H * W).reshape(H, W)
    if clear:
        acc[:, :] = light
    else:
        acc += light
    if gy.shape[1]:
        flux = amp * c_flux
        if grid_q > 0:
            acc += gy @ (flux.reshape(-1, grid_q) @ gxt)
        else:
            acc += (gy * flux[None, :]) @ gxt


# ---------------------------------------------------------------- sensor read-out


@njit(warm=_warm_expose)
def expose_window(out: np.ndarray, Y0: int, X0: int, acc: np.ndarray, ay: int, ax: int,
                  bg: np.ndarray, prnu: np.ndarray, by: int, bx: int, z: np.ndarray,
                  noise: bool, sensor: np.ndarray) -> None:
    """Read out the window out[Y0:Y0 + h, X0:X0 + w], (h, w) = z.shape (uint8).

    Photo-signal S = float32(acc[ay + i, ax + j]) + bg[by + i, bx + j] (DN); the sensor of
    :meth:`iscd.sim.sensor.SensorModel.expose` in the same float32 arithmetic:
    S *= prnu; if noise: S += sqrt(max(gain S + read2, 0)) z (z: N(0, 1) draws); S +=
    offset; clip to [0, top]; truncate. sensor: float32 (gain DN per electron, read2 read
    noise^2 DN^2, offset = dark + 0.5 DN, top DN), see :func:`sensor_constants`.
    """
    h, w = z.shape
    zero = np.float32(0.0)
    gain, read2, offset, top = sensor[0], sensor[1], sensor[2], sensor[3]
    for i in range(h):  # row views: indices provably >= 0, so the loop vectorizes
        o = out[Y0 + i, X0:X0 + w]
        a = acc[ay + i, ax:ax + w]
        b = bg[by + i, bx:bx + w]
        p = prnu[by + i, bx:bx + w]
        zi = z[i]
        for j in range(w):
            s = (np.float32(a[j]) + b[j]) * p[j]
            if noise:
                sd = s * gain + read2
                s = s + np.sqrt(max(sd, zero)) * zi[j]
            s = min(max(s + offset, zero), top)
            o[j] = np.uint8(s)


@njit(warm=_warm_window)
def render_window(out: np.ndarray, Y0: int, X0: int, acc: np.ndarray, ay: int, ax: int,
                  clear: bool, kern: np.ndarray, ix: np.ndarray, iy: np.ndarray,
                  w: np.ndarray, c_amp: float, c_core: float, c_flux: float,
                  gy: np.ndarray, gxt: np.ndarray, grid_q: int, bg: np.ndarray,
                  prnu: np.ndarray, by: int, bx: int, z: np.ndarray, noise: bool,
                  sensor: np.ndarray) -> None:
    """:func:`add_sources` of one source set (the last of its window) and
    :func:`expose_window`, fused: the set's glare is added row by row on the way to the
    sensor (the same sums: acc + glare, then float32)."""
    if clear:
        acc[:, :] = 0.0
    _add_cores(acc, kern, ix, iy, w, c_amp, c_core)
    m = gy.shape[1]
    if m > 0:
        t = _glare_t(w, c_amp, c_flux, gxt, grid_q, m)
        row = np.empty(acc.shape[1])
        for y in range(ay, ay + z.shape[0]):  # only the rows read out
            _glare_row(row, gy, y, t)
            a = acc[y]
            for x in range(row.size):
                a[x] += row[x]
    expose_window(out, Y0, X0, acc, ay, ax, bg, prnu, by, bx, z, noise, sensor)


def expose_window_ref(out: np.ndarray, Y0: int, X0: int, acc: np.ndarray, ay: int, ax: int,
                      bg: np.ndarray, prnu: np.ndarray, by: int, bx: int, z: np.ndarray,
                      noise: bool, sensor: np.ndarray) -> None:
    """Reference of :func:`expose_window` (numpy, the arithmetic of ``SensorModel.expose``
    with the draws ``z`` given).

    Parameters
    ----------
    out : ndarray of uint8
        (H, W) frame, written in the window only.
    Y0, X0 : int
        Top-left of the window in ``out``, px.
    acc : ndarray of float64
        (hc, wc) light canvas, DN.
    ay, ax : int
        Top-left of the window in ``acc``, px.
    bg : ndarray of float32
        Background photo-signal, DN.
    prnu : ndarray of float32
        PRNU gain map, the shape of ``bg``.
    by, bx : int
        Top-left of the window in ``bg`` and ``prnu``, px.
    z : ndarray of float32
        (h, w) N(0, 1) draws; (h, w) is the window's shape.
    noise : bool
        Add shot and read noise.
    sensor : ndarray of float32
        (4,) :func:`sensor_constants`.
    """
    gain, read2, offset, top = sensor
    h, w = z.shape
    s = np.add(acc[ay:ay + h, ax:ax + w], bg[by:by + h, bx:bx + w], dtype=np.float32)
    s *= prnu[by:by + h, bx:bx + w]
    if noise:
        sd = s * gain
        sd += read2
        np.maximum(sd, 0.0, out=sd)
        np.sqrt(sd, out=sd)
        sd *= z
        s += sd
    s += offset
    np.clip(s, 0.0, top, out=s)
    out[Y0:Y0 + h, X0:X0 + w] = s


def render_window_ref(out: np.ndarray, Y0: int, X0: int, acc: np.ndarray, ay: int, ax: int,
                      clear: bool, kern: np.ndarray, ix: np.ndarray, iy: np.ndarray,
                      w: np.ndarray, c_amp: float, c_core: float, c_flux: float,
                      gy: np.ndarray, gxt: np.ndarray, grid_q: int, bg: np.ndarray,
                      prnu: np.ndarray, by: int, bx: int, z: np.ndarray, noise: bool,
                      sensor: np.ndarray) -> None:
    """Reference of :func:`render_window`.

    Parameters
    ----------
    out : ndarray of uint8
        (H, W) frame, written in the window only.
    Y0, X0 : int
        Top-left of the window in ``out``, px.
    acc : ndarray of float64
        (hc, wc) light canvas, DN (modified in place).
    ay, ax : int
        Top-left of the window in ``acc``, px.
    clear : bool
        Set ``acc`` to 0 first.
    kern : ndarray of float32
        (n, k, k) core profile P of each source's window.
    ix, iy : ndarray of int64
        (n,) window origins, canvas px.
    w : ndarray of float64
        (n,) on-fraction (0..1) or flicker gain (0..2) of each source.
    c_amp : float
        Grey level of a fully-on source, DN.
    c_core : float
        Core peak scale per DN of light.
    c_flux : float
        Glare flux per DN of light, px^2.
    gy : ndarray of float64
        (hc, m) unit-area glare Gaussians of the source rows, 1/px (m = 0: no glare).
    gxt : ndarray of float64
        (q, wc) unit-area glare Gaussians of the source columns, 1/px.
    grid_q : int
        Columns of the row-major (m, grid_q) source grid; 0: m = q = n.
    bg : ndarray of float32
        Background photo-signal, DN.
    prnu : ndarray of float32
        PRNU gain map, the shape of ``bg``.
    by, bx : int
        Top-left of the window in ``bg`` and ``prnu``, px.
    z : ndarray of float32
        (h, w) N(0, 1) draws; (h, w) is the window's shape.
    noise : bool
        Add shot and read noise.
    sensor : ndarray of float32
        (4,) :func:`sensor_constants`.
    """
    add_sources_ref(acc, clear, kern, ix, iy, w, c_amp, c_core, c_flux, gy, gxt, grid_q)
    expose_window_ref(out, Y0, X0, acc, ay, ax, bg, prnu, by, bx, z, noise, sensor)


def warm_bloom_args() -> tuple:
    """Example arguments of :func:`bloom_columns` (compiled by ``Scene.warm_up`` only when
    the scene blooms, so the default scene's warm-up is unchanged)."""
    return (np.zeros((6, 4)), 255.0, 0.5, np.array([0.2, 0.05]))


@njit
def bloom_columns(acc: np.ndarray, cap: float, spill: float, coef: np.ndarray) -> None:
    """Blooming of the light canvas ``acc`` ((h, w) float64 DN) in place: a pixel above
    ``cap`` DN (full well) loses ``spill`` of its excess e and each pixel d rows above and
    below it in its column gains coef[d - 1] e (:func:`iscd.sim.sensor.bloom_coefficients`;
    spill = 2 sum coef). Same float64 operations, per pixel in the same order, as
    :func:`bloom_columns_ref`."""
    h, w = acc.shape
    ex = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            e = acc[y, x] - cap
            if e > 0.0:
                ex[y, x] = e
    for y in range(h):
        for x in range(w):
            acc[y, x] -= spill * ex[y, x]
    for j in range(coef.size):
        d = j + 1
        c = coef[j]
        for y in range(h - d):  # from the pixel d rows below
            for x in range(w):
                acc[y, x] += c * ex[y + d, x]
        for y in range(d, h):  # from the pixel d rows above
            for x in range(w):
                acc[y, x] += c * ex[y - d, x]


def bloom_columns_ref(acc: np.ndarray, cap: float, spill: float, coef: np.ndarray) -> None:
    """Reference of :func:`bloom_columns` (numpy).

    Parameters
    ----------
    acc : ndarray of float64
        (h, w) light canvas, DN (modified in place).
    cap : float
        Full well, DN.
    spill : float
        Share of the excess above ``cap`` that a pixel loses, 0..1.
    coef : ndarray of float64
        (D,) :func:`iscd.sim.sensor.bloom_coefficients`.
    """
    ex = np.maximum(acc - cap, 0.0)
    acc -= spill * ex
    for j in range(coef.size):
        d = j + 1
        c = coef[j]
        acc[:-d] += c * ex[d:]
        acc[d:] += c * ex[:-d]


def sensor_constants(gain_dn_per_e: float, read_dn: float, dark_dn: float, max_dn: int
                     ) -> np.ndarray:
    """The float32 constants of :meth:`iscd.sim.sensor.SensorModel.expose` for
    :func:`expose_window`: (gain, read_dn^2, dark_dn + 0.5, max_dn + 0.5 - 1e-3).

    Parameters
    ----------
    gain_dn_per_e : float
        Conversion gain, DN per electron.
    read_dn : float
        Read noise RMS, DN.
    dark_dn : float
        Black level, DN.
    max_dn : int
        Top grey level, DN.

    Returns
    -------
    ndarray of float32
        (4,) gain (DN/e), read noise^2 (DN^2), offset (DN), top (DN).
    """
    return np.array([gain_dn_per_e, read_dn ** 2, dark_dn + 0.5, max_dn + 0.5 - 1e-3],
                    np.float32)


def warm() -> None:
    """Compile (or load from the cache) the kernels of this module, with the argument types
    the scene passes (call before a real-time clock starts)."""
    copy_frame(*_warm_copy())
    add_residual_shift(*_warm_residual())
    add_sources(*_warm_sources())
    expose_window(*_warm_expose())
    render_window(*_warm_window())
