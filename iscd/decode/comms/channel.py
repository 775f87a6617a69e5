"""Channel estimation: what luminance each level produces, per camera and LED.

A frame's luminance is modelled as ``L = h_{c,i}(q) + noise`` where ``q`` is the (mixed)
level index seen by the exposure window (0 .. M-1; a clean frame of level s has q = s-1, a
frame straddling levels a and b with fraction alpha in a has q = alpha (a-1) + (1-alpha)
(b-1), i.e. the integrated PWM duty times M-1). ``h`` is the camera's response: linear
for an unsaturated camera, bending over where pixels clip (the f/4 camera of HDR). It is
represented by its values at the M levels (the *centroids* ``mu[c, i, s]``) and linear
interpolation between them; the noise by per-level variances ``var[c, i, s]``.

Two estimators (both from labelled clean frames: the header and training sequence of a
packet, and with ``decision_directed`` also the decided data symbols):

* :func:`estimate_dissertation` -- the dissertation's channel factors (3.11 / 4.2):
  ``w^s = mean(L^s) / s`` per camera, pooled over LEDs, so the centroid ``w^s s`` is the
  mean luminance of level s; unit variances and the Euclidean decision (3.12 / 4.3).
* :func:`estimate_iscd` -- the project's: pooled per-level centroids with a per-LED gain
  and offset (least squares, shrunk towards the pooled curve), per-LED per-level
  corrections shrunk by their sample count, per-level noise variances from the residuals
  (shrunk towards the camera's pooled variance, with a floor) and a per-LED noise scale.
  The decision is then the Gaussian (or Student-t) maximum likelihood summed over both
  cameras: a camera whose centroids merge (saturation) or that is noisy contributes little,
  so one rule does diversity (equal apertures) and HDR (different apertures).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from iscd.core.jit import njit

KINDS = ("gauss", "t", "euclid")


@njit(warm=lambda: (np.ones((1, 2, 3)), 4), error_model="numpy")
def _fine_table(table: np.ndarray, fine: int) -> np.ndarray:
    """Linear interpolation of ``table`` (C, N, M) at q = g / fine, g = 0 .. (M - 1) fine,
    as float32 (C, N * G): :meth:`ChannelModel.interp` element by element."""
    C, N, M = table.shape
    G = (M - 1) * fine + 1
    out = np.empty((C, N * G), np.float32)
    # the segment and the fraction of each q (the same for every row)
    js = np.empty(G, np.int64)
    fs = np.empty(G)
    for g in range(G):
        q = g / fine
        q0 = min(max(np.floor(q), 0.0), M - 2.0) if M >= 2 else 0.0
        js[g] = int(q0)
        fs[g] = q - js[g]
    for c in range(C):
        for i in range(N):
            row = table[c, i]
            o = out[c, i * G:(i + 1) * G]
            for g in range(G):
                j = js[g]
                a = row[j]
                b = row[j + 1] if M >= 2 else a
                o[g] = np.float32(a + fs[g] * (b - a))
    return out


@njit(warm=lambda: (np.ones((1, 2, 3)), np.ones((1, 2, 3)), 4), error_model="numpy")
def _fine_tables(mu: np.ndarray, var: np.ndarray, fine: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_fine_table` of the centroids and of the variances, in one call."""
    return _fine_table(mu, fine), _fine_table(var, fine)


@njit(warm=lambda: (np.ones((1, 2, 3)), 0.02), error_model="numpy")
def _step_gain(mu: np.ndarray, ts_e: float) -> np.ndarray:
    """(C, N) float32 ``((mu_M - mu_1) / max(M - 1, 1) * ts_e)`` of mu (C, N, M) float64
    (:meth:`ChannelModel._straddle_gain`, element by element)."""
    C, N, M = mu.shape
    out = np.empty((C, N), np.float32)
    d = float(max(M - 1, 1))
    for c in range(C):
        for i in range(N):
            out[c, i] = np.float32((mu[c, i, M - 1] - mu[c, i, 0]) / d * ts_e)
    return out


@njit(warm=lambda: (np.ones((1, 2, 4)),), error_model="numpy")
def _interp_error_kernel(mu: np.ndarray) -> np.ndarray:
    """:attr:`ChannelModel.interp_error` of centroids mu (C, N, M), M >= 2, element by
    element: 0.125 max(|slope change| at the segment's two ends (0 beyond the outer knots))."""
    C, N, M = mu.shape
    out = np.empty((C, N, M - 1))
    for c in range(C):
        for i in range(N):
            row = mu[c, i]
            for j in range(M - 1):
                left = abs((row[j + 1] - row[j]) - (row[j] - row[j - 1])) if j > 0 else 0.0
                right = abs((row[j + 2] - row[j + 1]) - (row[j + 1] - row[j])) if j < M - 2 else 0.0
                out[c, i, j] = 0.125 * np.maximum(left, right)
    return out


@dataclass(frozen=True)
class ChannelModel:
    """Per camera c, LED i and level s (0-based): centroid ``mu`` (DN), variance ``var`` (DN^2).

    kind: ``"gauss"`` (cost (L-mu)^2/var + log var), ``"t"`` (Student-t with ``nu`` degrees of
    freedom: heavier tails, robust to model errors), ``"euclid"`` ((L-mu)^2, the
    dissertation's rule 3.12 / 4.3; ``var`` ignored).
    """

    mu: np.ndarray  # (C, N, M)
    var: np.ndarray  # (C, N, M)
    kind: str = "gauss"
    nu: float = 6.0

    @property
    def n_cams(self) -> int:
        return int(self.mu.shape[0])

    @property
    def n_leds(self) -> int:
        return int(self.mu.shape[1])

    @property
    def levels(self) -> int:
        return int(self.mu.shape[2])

    def interp(self, table: np.ndarray, q: np.ndarray, led_axis: int = -1
               ) -> tuple[np.ndarray, np.ndarray]:
        """Linear interpolation of ``table`` (C, N, M) at fractional level indices ``q``.

        Parameters
        ----------
        table : ndarray
            (C, N, M) values per camera, LED and level (e.g. ``mu``, DN, or ``var``, DN^2).
        q : ndarray
            Fractional level indices, 0 .. M-1 (extrapolated from the outer segments beyond),
            with the LED axis (length N) at ``led_axis``.
        led_axis : int
            The axis of ``q`` that indexes the LEDs.

        Returns
        -------
        values : ndarray of float64
            (C,) + q.shape, the units of ``table``.
        slopes : ndarray of float64
            (C,) + q.shape, per unit of q.
        """
        C, N, M = table.shape
        q = np.asarray(q, dtype=np.float64)
        q0 = np.clip(np.floor(q), 0, M - 2).astype(np.intp)
        f = q - q0
        shape = [1] * q.ndim
        shape[led_axis] = N
        idx = q0 + (np.arange(N) * M).reshape(shape)
        flat = table.reshape(C, N * M)
        a = flat[:, idx]
        slope = flat[:, idx + 1] - a
        return a + f * slope, slope

    FINE = 32
    """Sub-steps per level of the lookup tables of :meth:`lookup`."""

    def _fine_reference(self) -> tuple[np.ndarray, np.ndarray]:
        """Pure-numpy reference of :attr:`_fine`."""
        C, N, M = self.mu.shape
        q = np.arange((M - 1) * self.FINE + 1) / self.FINE
        qq = np.broadcast_to(q, (N, q.size))
        mu, _ = self.interp(self.mu, qq, led_axis=0)
        var, _ = self.interp(self.var, qq, led_axis=0)
        return mu.reshape(C, -1).astype(np.float32), var.reshape(C, -1).astype(np.float32)

    @cached_property
    def _fine(self) -> tuple[np.ndarray, np.ndarray]:
        """Centroids and variances (C, N * G) float32 at the G = (M - 1) * FINE + 1 fractional
        levels q = g / FINE of every LED (compiled :func:`_fine_table`, bit-identical to
        :meth:`_fine_reference`)."""
        mu = np.ascontiguousarray(self.mu, dtype=np.float64)
        var = np.ascontiguousarray(self.var, dtype=np.float64)
        return _fine_tables(mu, var, self.FINE)

    @cached_property
    def interp_error(self) -> np.ndarray:
        """(C, N, M-1) RMS error bound of the linear interpolation within each level
        segment, from the change of slope at its ends (curvature of the response h)."""
        if self.mu.ndim == 3 and self.mu.shape[2] >= 2 and self.mu.dtype == np.float64:
            return _interp_error_kernel(np.ascontiguousarray(self.mu))
        s = np.diff(self.mu, axis=-1)
        ds = np.abs(np.diff(s, axis=-1))  # (C, N, M-2) slope change at inner knots
        pad = np.zeros(ds.shape[:-1] + (1,))
        left = np.concatenate([pad, ds], -1)
        right = np.concatenate([ds, pad], -1)
        return 0.125 * np.maximum(left, right)

    @cached_property
    def _interp_error32(self) -> np.ndarray:
        return self.interp_error.reshape(self.n_cams, -1).astype(np.float32)

    @cached_property
    def _memo(self) -> dict:
        """Derived arrays keyed by their parameters (:meth:`_straddle_gain`)."""
        return {}

    def _straddle_gain(self, ts_e: float) -> np.ndarray:
        """(C, N) float32 ``(mu_M - mu_1) / (M - 1) * ts_e``: the response's change per frame
        of boundary error (ts_e = timing_sigma / e) per level step (:func:`decide_span`)."""
        key = ("gain", ts_e)
        g = self._memo.get(key)
        if g is None:
            mu = self.mu
            if mu.dtype == np.float64 and mu.ndim == 3 and mu.shape[2] >= 1:
                g = _step_gain(np.ascontiguousarray(mu), float(ts_e))
            else:
                g = ((mu[:, :, -1] - mu[:, :, 0]) / max(self.levels - 1, 1) * ts_e).astype(np.float32)
            self._memo[key] = g
        return g

    @cached_property
    def _tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """float32 centroids, 1 / variances and log variances (C, N, M)."""
        v = self.var.astype(np.float64)
        return (self.mu.astype(np.float32), (1.0 / v).astype(np.float32),
                np.log(v).astype(np.float32))

    def lookup(self, q: np.ndarray, led_axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
        """Centroid and variance (float32) at fractional level indices q.

        From tables with 1/32-level steps (nearest entry: one gather each, for speed).

        Parameters
        ----------
        q : ndarray
            Fractional level indices, 0 .. M-1 (clipped), with the LED axis (length N) at
            ``led_axis``. Not modified.
        led_axis : int
            The axis of ``q`` that indexes the LEDs.

        Returns
        -------
        mu : ndarray of float32
            (C,) + q.shape centroids, DN.
        var : ndarray of float32
            (C,) + q.shape variances, DN^2.
        """
        C, N, M = self.mu.shape
        G = (M - 1) * self.FINE + 1
        shape = [1] * np.ndim(q)
        shape[led_axis] = N
        x = np.clip(q, 0, M - 1)
        x *= self.FINE
        x += 0.5
        idx = x.astype(np.intp)  # round half up (x >= 0)
        idx += (np.arange(N) * G).reshape(shape)
        mu_t, var_t = self._fine
        return np.take(mu_t, idx, axis=1), np.take(var_t, idx, axis=1)

    def interp_error_at(self, q: np.ndarray, led_axis: int = -1) -> np.ndarray:
        """:attr:`interp_error` (float32) of the segments holding fractional levels q.

        Parameters
        ----------
        q : ndarray
            Fractional level indices, 0 .. M-1 (clipped), with the LED axis (length N) at
            ``led_axis``.
        led_axis : int
            The axis of ``q`` that indexes the LEDs.

        Returns
        -------
        ndarray of float32
            (C,) + q.shape RMS interpolation error bounds, DN.
        """
        C, N, M = self.mu.shape
        shape = [1] * np.ndim(q)
        shape[led_axis] = N
        seg = np.clip(q, 0, M - 2).astype(np.intp)  # floor for q >= 0
        seg += (np.arange(N) * (M - 1)).reshape(shape)
        return np.take(self._interp_error32, seg, axis=1)

    def _combine(self, r2: np.ndarray, ivar: np.ndarray, logvar: np.ndarray | float,
                 L: np.ndarray) -> np.ndarray:
        """Per-camera costs from squared residuals (modified in place), summed over cameras;
        entries of NaN observations (L's non-singleton leading axes) cost nothing."""
        if self.kind == "t":
            r2 *= ivar
            r2 *= np.float32(1.0 / self.nu)
            np.log1p(r2, out=r2)
            r2 *= np.float32(self.nu + 1.0)
            r2 += logvar
        elif self.kind == "gauss":
            r2 *= ivar
            r2 += logvar
        bad = np.isnan(L)
        while bad.ndim and bad.shape[-1] == 1:
            bad = bad[..., 0]
        if bad.any():
            r2[bad] = 0.0
        return r2.sum(axis=0) if r2.shape[0] > 1 else r2[0]

    def cost(self, L: np.ndarray, mu: np.ndarray, var: np.ndarray) -> np.ndarray:
        """Negative log-likelihood (x2, up to a constant) of L given mu, var, summed over cameras.

        NaN observations cost nothing. With ``kind="euclid"`` this is the squared distance of the
        dissertation's decision rule.

        Parameters
        ----------
        L : ndarray
            (C, ...) observed luminance, DN (NaN = missing); broadcasts against ``mu`` over
            trailing axes.
        mu : ndarray
            (C, ...) centroids, DN.
        var : ndarray
            (C, ...) variances, DN^2 (ignored for ``"euclid"``); may be overwritten.

        Returns
        -------
        ndarray of float32
            The cost, the broadcast shape without the camera axis 0.

        References
        ----------
        Dissertation, eqs. (3.12), (4.3) (``"euclid"``).
        """
        L = np.asarray(L, dtype=np.float32)
        r2 = np.subtract(L, mu, dtype=np.float32)
        np.square(r2, out=r2)
        if self.kind == "euclid":
            return self._combine(r2, np.float32(1.0), 0.0, L)
        var = np.asarray(var, dtype=np.float32)
        ivar = np.reciprocal(var)
        return self._combine(r2, ivar, np.log(var, out=var), L)

    def level_cost(self, L: np.ndarray) -> np.ndarray:
        """Cost (n, N, M) of each level for clean observations L (C, n, N).

        Parameters
        ----------
        L : ndarray
            (C, n, N) clean-frame luminance, DN (NaN = missing).

        Returns
        -------
        ndarray of float32
            (n, N, M) cost of each 0-based level, summed over cameras.

        References
        ----------
        Dissertation, eqs. (3.12), (4.3) (``"euclid"``).
        """
        mu, ivar, logvar = self._tables
        L = np.asarray(L, dtype=np.float32)
        r2 = np.square(L[..., None] - mu[:, None])
        return self._combine(r2, ivar[:, None], logvar[:, None], L)


def _stats(y: np.ndarray, lev: np.ndarray, N: int, M: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Counts, sums and sums of squares per (LED, level) of samples y (n, N), levels (n, N)."""
    ok = np.isfinite(y) & (lev >= 0) & (lev < M)
    idx = (np.arange(N)[None, :] * M + lev)[ok]
    yv = y[ok]
    n = np.bincount(idx, minlength=N * M).reshape(N, M).astype(np.float64)
    s = np.bincount(idx, weights=yv, minlength=N * M).reshape(N, M)
    q = np.bincount(idx, weights=yv * yv, minlength=N * M).reshape(N, M)
    return n, s, q


def _fill_levels(m: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Levels never seen get values interpolated (clamped) from the seen ones (M,)."""
    if seen.all() or not seen.any():
        return m if seen.any() else np.zeros_like(m)
    x = np.flatnonzero(seen)
    return np.interp(np.arange(m.size), x, m[x])


def estimate_dissertation(y: np.ndarray, lev: np.ndarray, M: int) -> ChannelModel:
    """Channel factors (3.11 / 4.2): centroid ``w^s s = mean over LEDs and samples of L^s``.

    Same centroids for every LED of a camera.

    Parameters
    ----------
    y : ndarray
        (C, n, N) clean-frame luminance of labelled symbols, DN (NaN = missing).
    lev : ndarray
        (n, N) their 0-based levels (-1 = unlabelled).
    M : int
        Number of levels.

    Returns
    -------
    ChannelModel
        ``kind="euclid"``, centroids (C, N, M) DN, unit variances.

    References
    ----------
    Dissertation, eqs. (3.11), (4.2); decision (3.12), (4.3).
    """
    C, _, N = y.shape
    mu = np.zeros((C, N, M))
    for c in range(C):
        n, s, _ = _stats(y[c], lev, N, M)
        cnt = n.sum(0)
        m = np.where(cnt > 0, s.sum(0) / np.maximum(cnt, 1), 0.0)
        mu[c] = _fill_levels(m, cnt > 0)[None, :]
    return ChannelModel(mu=mu, var=np.ones_like(mu), kind="euclid")


@dataclass(frozen=True)
class IscdChannelSettings:
    """Shrinkage and floors of :func:`estimate_iscd` (pseudo-sample counts, DN)."""

    led_prior: float = 4.0  # pseudo-samples pulling each LED's gain/offset to the pooled curve
    level_prior: float = 3.0  # pseudo-samples pulling a per-LED centroid to its affine model
    var_prior: float = 10.0  # pseudo-samples pulling a level's variance to the camera's
    led_var_prior: float = 10.0  # pseudo-samples pulling an LED's noise scale to 1
    var_floor_dn: float = 0.3  # smallest noise RMS, DN
    outlier_sigma: float = 6.0  # samples further than this from their centroid are dropped


def _estimate_camera(y: np.ndarray, lev: np.ndarray, M: int, st: IscdChannelSettings
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    N = y.shape[1]
    n, s, q = _stats(y, lev, N, M)
    cnt = n.sum(0)
    if (cnt > 0).sum() < 2:
        return None
    m = _fill_levels(np.where(cnt > 0, s.sum(0) / np.maximum(cnt, 1), 0.0), cnt > 0)
    a = np.ones(N)
    b = np.zeros(N)
    lam = st.led_prior / M
    for _ in range(2):
        # per-LED affine fit y ~ a_i m_s + b_i, with lam pseudo-samples per level on the pooled curve
        n1 = n + lam
        s1 = s + lam * m[None, :]
        W = n1.sum(1)
        Sm = n1 @ m
        Smm = n1 @ (m * m)
        Sy = s1.sum(1)
        Smy = s1 @ m
        den = W * Smm - Sm * Sm
        a = np.where(den > 1e-12, (W * Smy - Sm * Sy) / np.where(den > 1e-12, den, 1.0), 1.0)
        b = (Sy - a * Sm) / W
        # pooled curve given the LEDs' gains/offsets
        wn = (a * a)[:, None] * n
        num = (a[:, None] * (s - n * b[:, None])).sum(0)
        den_m = wn.sum(0)
        seen = den_m > 0
        m = _fill_levels(np.where(seen, num / np.where(seen, den_m, 1.0), 0.0), seen)
        # fix the gauge: mean gain 1, mean offset 0
        am, bm = a.mean(), b.mean()
        if am > 1e-9:
            m = am * m + bm
            a = a / am
            b = b - a * bm
    base = a[:, None] * m[None, :] + b[:, None]
    mean_is = np.where(n > 0, s / np.maximum(n, 1), base)
    mu = base + n / (n + st.level_prior) * (mean_is - base)
    ssr = np.maximum(q - 2 * mu * s + n * mu * mu, 0.0)
    dof = n - n / (n + st.level_prior)
    floor = st.var_floor_dn ** 2
    v_all = max(ssr.sum() / max(dof.sum(), 1.0), floor)
    dof_s = dof.sum(0)
    v_s = (ssr.sum(0) + st.var_prior * v_all) / (dof_s + st.var_prior)
    v_s = np.maximum(v_s, floor)
    t_i = ((ssr / v_s[None, :]).sum(1) + st.led_var_prior) / (dof.sum(1) + st.led_var_prior)
    var = np.maximum(t_i[:, None] * v_s[None, :], floor)
    return mu, var


def _median_by_level(r: np.ndarray, lv: np.ndarray, M: int) -> np.ndarray:
    """Median of r per level 0..M-1 (NaN for a level without samples), by one sort."""
    top = float(r.max()) if r.size else 0.0
    order = np.argsort(lv + r / (top * 1.001 + 1e-300), kind="stable")  # level, then residual
    cnt = np.bincount(lv, minlength=M)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    rs = r[order]
    lo = rs[np.minimum(start + (cnt - 1) // 2, max(rs.size - 1, 0))] if rs.size else np.zeros(M)
    hi = rs[np.minimum(start + cnt // 2, max(rs.size - 1, 0))] if rs.size else np.zeros(M)
    return np.where(cnt > 0, 0.5 * (lo + hi), np.nan)


@njit
def _fill_levels_k(m: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """:func:`_fill_levels` (compiled)."""
    n_seen = 0
    for s in range(m.size):
        if seen[s]:
            n_seen += 1
    if n_seen == 0:
        return np.zeros_like(m)
    if n_seen == m.size:
        return m
    x = np.empty(n_seen)
    v = np.empty(n_seen)
    j = 0
    for s in range(m.size):
        if seen[s]:
            x[j] = s
            v[j] = m[s]
            j += 1
    return np.interp(np.arange(m.size).astype(np.float64), x, v)


@njit
def _camera_kernel(y: np.ndarray, lev: np.ndarray, M: int, led_prior: float, level_prior: float,
                   var_prior: float, led_var_prior: float, var_floor_dn: float
                   ) -> tuple[bool, np.ndarray, np.ndarray]:
    """:func:`_estimate_camera` (compiled): (usable, centroids (N, M), variances (N, M)) of
    one camera's samples y (n, N) DN (NaN = missing), levels lev (n, N) (-1 = unknown).
    Sums run in sample order (numpy: pairwise), agreement ~1e-13 relative."""
    n_s, N = y.shape
    n = np.zeros((N, M))
    s = np.zeros((N, M))
    q = np.zeros((N, M))
    for t in range(n_s):
        for i in range(N):
            lv = lev[t, i]
            v = y[t, i]
            if lv >= 0 and lv < M and np.isfinite(v):
                n[i, lv] += 1.0
                s[i, lv] += v
                q[i, lv] += v * v
    cnt = np.zeros(M)
    ssum = np.zeros(M)
    for i in range(N):
        for l in range(M):
            cnt[l] += n[i, l]
            ssum[l] += s[i, l]
    n_lev = 0
    for l in range(M):
        if cnt[l] > 0:
            n_lev += 1
    if n_lev < 2:
        return False, np.zeros((N, M)), np.zeros((N, M))
    m = np.zeros(M)
    for l in range(M):
        m[l] = ssum[l] / max(cnt[l], 1.0) if cnt[l] > 0 else 0.0
    m = _fill_levels_k(m, cnt > 0)
    a = np.ones(N)
    b = np.zeros(N)
    lam = led_prior / M
    for _ in range(2):
        # per-LED affine fit y ~ a_i m_s + b_i, lam pseudo-samples per level on the pooled curve
        for i in range(N):
            W = 0.0
            Sm = 0.0
            Smm = 0.0
            Sy = 0.0
            Smy = 0.0
            for l in range(M):
                n1 = n[i, l] + lam
                s1 = s[i, l] + lam * m[l]
                W += n1
                Sm += n1 * m[l]
                Smm += n1 * (m[l] * m[l])
                Sy += s1
                Smy += s1 * m[l]
            den = W * Smm - Sm * Sm
            a[i] = (W * Smy - Sm * Sy) / den if den > 1e-12 else 1.0
            b[i] = (Sy - a[i] * Sm) / W
        # pooled curve given the LEDs' gains/offsets
        num = np.zeros(M)
        den_m = np.zeros(M)
        for i in range(N):
            for l in range(M):
                num[l] += a[i] * (s[i, l] - n[i, l] * b[i])
                den_m[l] += (a[i] * a[i]) * n[i, l]
        seen = den_m > 0
        for l in range(M):
            m[l] = num[l] / den_m[l] if seen[l] else 0.0
        m = _fill_levels_k(m, seen)
        am = a.mean()
        bm = b.mean()
        if am > 1e-9:  # fix the gauge: mean gain 1, mean offset 0
            m = am * m + bm
            a = a / am
            b = b - a * bm
    mu = np.empty((N, M))
    ssr = np.empty((N, M))
    dof = np.empty((N, M))
    ssr_all = 0.0
    dof_all = 0.0
    ssr_l = np.zeros(M)
    dof_l = np.zeros(M)
    for i in range(N):
        for l in range(M):
            base = a[i] * m[l] + b[i]
            nn = n[i, l]
            mean_is = s[i, l] / max(nn, 1.0) if nn > 0 else base
            u = base + nn / (nn + level_prior) * (mean_is - base)
            mu[i, l] = u
            r = max(q[i, l] - 2 * u * s[i, l] + nn * u * u, 0.0)
            ssr[i, l] = r
            d = nn - nn / (nn + level_prior)
            dof[i, l] = d
            ssr_all += r
            dof_all += d
            ssr_l[l] += r
            dof_l[l] += d
    floor = var_floor_dn ** 2
    v_all = max(ssr_all / max(dof_all, 1.0), floor)
    v_s = np.empty(M)
    for l in range(M):
        v_s[l] = max((ssr_l[l] + var_prior * v_all) / (dof_l[l] + var_prior), floor)
    var = np.empty((N, M))
    for i in range(N):
        num_t = 0.0
        dof_i = 0.0
        for l in range(M):
            num_t += ssr[i, l] / v_s[l]
            dof_i += dof[i, l]
        t_i = (num_t + led_var_prior) / (dof_i + led_var_prior)
        for l in range(M):
            var[i, l] = max(t_i * v_s[l], floor)
    return True, mu, var


@njit(inline="always")
def _select_kth(a: np.ndarray, lo: int, hi: int, k: int) -> float:
    """The k-th smallest value of a[lo:hi] (k absolute, lo <= k < hi; no NaN), moving the
    smaller ones to a[lo:k] (a quickselect in place: the values are what a sort gives;
    numba's np.partition, which copies and is NaN-aware, took most of :func:`_iscd_camera`)."""
    left = lo
    right = hi - 1
    while right > left:
        m = (left + right) >> 1
        if a[m] < a[left]:
            a[m], a[left] = a[left], a[m]
        if a[right] < a[left]:
            a[right], a[left] = a[left], a[right]
        if a[right] < a[m]:
            a[right], a[m] = a[m], a[right]
        piv = a[m]
        i = left
        j = right
        while i <= j:
            while a[i] < piv:
                i += 1
            while piv < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            right = j
        elif k >= i:
            left = i
        else:
            break
    return a[k]


def _warm_iscd() -> tuple:
    y = np.arange(24.0).reshape(12, 2)
    lev = (np.arange(24).reshape(12, 2) % 3).astype(np.int64)
    return (y, lev, 3, 4.0, 3.0, 10.0, 10.0, 0.3, 6.0)


@njit
def _outliers_exact(y: np.ndarray, lev: np.ndarray, M: int, r: np.ndarray, cnt: np.ndarray,
                    var_floor_dn: float, outlier_sigma: float) -> tuple[np.ndarray, bool]:
    """y with the outliers of :func:`_iscd_camera` set to NaN, and whether there were any:
    residuals r (n, N) bucketed by level (counting sort, cnt (M,) per level), each level's
    median by selection, every sample compared with its level's threshold."""
    n_s, N = y.shape
    start = np.zeros(M + 1, np.int64)
    for l in range(M):
        start[l + 1] = start[l] + cnt[l]
    fill_at = start[:M].copy()
    vals = np.empty(start[M])
    for t in range(n_s):
        for i in range(N):
            lv = lev[t, i]
            rv = r[t, i]
            if lv >= 0 and np.isfinite(rv):
                lv = min(lv, M - 1)
                vals[fill_at[lv]] = rv
                fill_at[lv] += 1
    med = np.full(M, np.nan)
    for l in range(M):
        c_l = cnt[l]
        if c_l == 0:
            continue
        med[l] = _bucket_median(vals, start[l], start[l + 1])
    fin = np.isfinite(med)
    fill = np.nanmedian(med) if fin.any() else 1.0
    any_bad = False
    yb = y.copy()
    for t in range(n_s):
        for i in range(N):
            if lev[t, i] < 0 or not np.isfinite(r[t, i]):
                continue
            lv = min(lev[t, i], M - 1)
            md = med[lv] if fin[lv] else fill
            sd = max(1.4826 * md, var_floor_dn)
            if r[t, i] > outlier_sigma * sd:
                yb[t, i] = np.nan
                any_bad = True
    return yb, any_bad


@njit(inline="always")
def _bucket_median(vals: np.ndarray, a0: int, a1: int) -> float:
    """Median of vals[a0:a1] (reordered): the mean of the two middle values, as a sort gives."""
    c_l = a1 - a0
    kk = a0 + c_l // 2
    hi = _select_kth(vals, a0, a1, kk)  # vals[a0:kk] <= hi now
    if c_l % 2 == 1:
        lo = hi
    else:
        lo = vals[a0]
        for q in range(a0 + 1, kk):
            lo = max(lo, vals[q])
    return 0.5 * (lo + hi)


@njit
def _outliers(y: np.ndarray, lev: np.ndarray, M: int, r: np.ndarray, cnt: np.ndarray,
              var_floor_dn: float, outlier_sigma: float) -> tuple[np.ndarray, bool]:
    """:func:`_outliers_exact` without most medians: a level's median only matters through
    the comparisons ``r > outlier_sigma * max(1.4826 median, floor)``, monotonic in the
    median, so a bracket of it decides every sample outside the bracket's thresholds. The
    bracket: the binary exponents of the two middle values (a histogram of the residuals'
    exponents per level, one pass); a level with a sample between its two thresholds (rare:
    a residual within a factor 2 of the outlier threshold) gets its exact median by
    selection (branchy: selecting every median took 3/4 of :func:`_iscd_camera`). The
    same samples are dropped as :func:`_outliers_exact` drops."""
    n_s, N = y.shape
    NB = 2048
    hist = np.zeros((M, NB), np.int64)
    emin = np.full(M, NB, np.int64)
    emax = np.full(M, -1, np.int64)
    ri = r.reshape(-1).view(np.int64)
    for t in range(n_s):
        for i in range(N):
            lv = lev[t, i]
            rv = r[t, i]
            if lv >= 0 and np.isfinite(rv):
                lv = min(lv, M - 1)
                ex = (ri[t * N + i] >> 52) & 0x7FF
                hist[lv, ex] += 1
                emin[lv] = min(emin[lv], ex)
                emax[lv] = max(emax[lv], ex)
    thr_lo = np.zeros(M)
    thr_hi = np.zeros(M)
    edge = np.zeros(2, np.int64)
    edge_f = edge.view(np.float64)
    for l in range(M):
        c_l = cnt[l]
        if c_l == 0:
            continue
        if emax[l] >= 2045:  # the two middle values might overflow their sum
            return _outliers_exact(y, lev, M, r, cnt, var_floor_dn, outlier_sigma)
        ra = (c_l - 1) // 2  # the two middle order statistics (0-based)
        rb = c_l // 2
        ea = -1
        eb = -1
        acc = 0
        for ex in range(emin[l], emax[l] + 1):
            acc += hist[l, ex]
            if ea < 0 and acc > ra:
                ea = ex
            if acc > rb:
                eb = ex
                break
        edge[0] = ea << 52  # <= every value of exponent ea: <= the lower middle value
        edge[1] = (eb + 1) << 52  # > every value of exponent eb: > the upper one
        thr_lo[l] = outlier_sigma * max(1.4826 * edge_f[0], var_floor_dn)
        thr_hi[l] = outlier_sigma * max(1.4826 * edge_f[1], var_floor_dn)
    any_bad = False
    amb = np.zeros(M, np.bool_)
    yb = y.copy()
    for t in range(n_s):
        for i in range(N):
            lv = lev[t, i]
            rv = r[t, i]
            if lv < 0 or not np.isfinite(rv):
                continue
            lv = min(lv, M - 1)
            if rv > thr_hi[lv]:
                yb[t, i] = np.nan
                any_bad = True
            elif rv > thr_lo[lv]:
                amb[lv] = True
    for l in range(M):
        if not amb[l]:
            continue
        vals = np.empty(cnt[l])
        j = 0
        for t in range(n_s):
            for i in range(N):
                if lev[t, i] >= 0 and min(lev[t, i], M - 1) == l and np.isfinite(r[t, i]):
                    vals[j] = r[t, i]
                    j += 1
        md = _bucket_median(vals, 0, j)
        thr = outlier_sigma * max(1.4826 * md, var_floor_dn)
        for t in range(n_s):
            for i in range(N):
                if lev[t, i] >= 0 and min(lev[t, i], M - 1) == l and r[t, i] > thr:
                    yb[t, i] = np.nan
                    any_bad = True
    return yb, any_bad


@njit(warm=_warm_iscd)
def _iscd_camera(y: np.ndarray, lev: np.ndarray, M: int, led_prior: float, level_prior: float,
                 var_prior: float, led_var_prior: float, var_floor_dn: float, outlier_sigma: float
                 ) -> tuple[bool, np.ndarray, np.ndarray]:
    """One camera of :func:`estimate_iscd` (compiled): :func:`_camera_kernel`, then with
    ``outlier_sigma`` > 0 the samples further than outlier_sigma robust RMS (1.4826 x the
    median |residual| of their level over all LEDs) from their centroid dropped
    (:func:`_outliers`) and the model fitted again."""
    ok_fit, mu, var = _camera_kernel(y, lev, M, led_prior, level_prior, var_prior,
                                     led_var_prior, var_floor_dn)
    if not ok_fit or outlier_sigma <= 0:
        return ok_fit, mu, var
    n_s, N = y.shape
    r = np.empty((n_s, N))
    cnt = np.zeros(M, np.int64)
    for t in range(n_s):
        for i in range(N):
            lv = min(max(lev[t, i], 0), M - 1)
            r[t, i] = abs(y[t, i] - mu[i, lv])
            if np.isfinite(r[t, i]) and lev[t, i] >= 0:
                cnt[lv] += 1
    yb, any_bad = _outliers(y, lev, M, r, cnt, var_floor_dn, outlier_sigma)
    if any_bad:
        ok2, mu2, var2 = _camera_kernel(yb, lev, M, led_prior, level_prior, var_prior,
                                        led_var_prior, var_floor_dn)
        if ok2:
            return True, mu2, var2
    return True, mu, var


def estimate_iscd(y: np.ndarray, lev: np.ndarray, M: int,
                  settings: IscdChannelSettings | None = None, kind: str = "gauss",
                  nu: float = 6.0) -> ChannelModel:
    """The project's channel model (module docstring) from labelled clean samples.

    A camera without usable samples gets flat centroids and a huge variance (it then
    contributes nothing to decisions). Compiled per camera (:func:`_iscd_camera`);
    :func:`estimate_iscd_reference` is the specification.

    Parameters
    ----------
    y : ndarray
        (C, n, N) luminance, DN (NaN = missing).
    lev : ndarray
        (n, N) 0-based levels (-1 = unknown).
    M : int
        Number of levels.
    settings : IscdChannelSettings, optional
        Shrinkage and floors (default :class:`IscdChannelSettings()`).
    kind : {"gauss", "t", "euclid"}
        Cost of the returned model.
    nu : float
        Degrees of freedom of the Student-t cost.

    Returns
    -------
    ChannelModel
        Centroids ``mu`` (C, N, M), DN, and variances ``var`` (C, N, M), DN^2.
    """
    st = settings or IscdChannelSettings()
    C, _, N = y.shape
    mu = np.zeros((C, N, M))
    var = np.full((C, N, M), 1e12)
    levc = np.ascontiguousarray(lev, dtype=np.int64)
    for c in range(C):
        ok, mu_c, var_c = _iscd_camera(np.ascontiguousarray(y[c], dtype=np.float64), levc, int(M),
                                       float(st.led_prior), float(st.level_prior),
                                       float(st.var_prior), float(st.led_var_prior),
                                       float(st.var_floor_dn), float(st.outlier_sigma))
        if ok:
            mu[c], var[c] = mu_c, var_c
    return ChannelModel(mu=mu, var=var, kind=kind, nu=nu)


def estimate_iscd_reference(y: np.ndarray, lev: np.ndarray, M: int,
                  settings: IscdChannelSettings | None = None, kind: str = "gauss",
                  nu: float = 6.0) -> ChannelModel:
    """Pure-numpy reference of :func:`estimate_iscd` (the compiled kernel's specification).

    The project's channel model (module docstring) from labelled clean samples.
    A camera without usable samples gets flat centroids and a huge variance (it then
    contributes nothing to decisions).

    Parameters
    ----------
    y : ndarray
        (C, n, N) luminance, DN (NaN = missing).
    lev : ndarray
        (n, N) 0-based levels (-1 = unknown).
    M : int
        Number of levels.
    settings : IscdChannelSettings, optional
        Shrinkage and floors (default :class:`IscdChannelSettings()`).
    kind : {"gauss", "t", "euclid"}
        Cost of the returned model.
    nu : float
        Degrees of freedom of the Student-t cost.

    Returns
    -------
    ChannelModel
        Centroids ``mu`` (C, N, M), DN, and variances ``var`` (C, N, M), DN^2.
    """
    st = settings or IscdChannelSettings()
    C, _, N = y.shape
    mu = np.zeros((C, N, M))
    var = np.full((C, N, M), 1e12)
    for c in range(C):
        res = _estimate_camera(y[c], lev, M, st)
        if res is None:
            continue
        mu_c, var_c = res
        if st.outlier_sigma > 0:  # drop gross outliers (decision errors, glitches) and refit
            lv = np.clip(lev, 0, M - 1)
            r = np.abs(y[c] - np.take_along_axis(mu_c, lv.T, axis=1).T)
            ok = np.isfinite(r) & (lev >= 0)
            # robust scale per level: 1.4826 x median |residual| over all LEDs
            med = _median_by_level(r[ok], lv[ok], M)
            med = np.where(np.isfinite(med), med, np.nanmedian(med) if np.isfinite(med).any() else 1.0)
            sd = np.maximum(1.4826 * med, st.var_floor_dn)
            bad = ok & (r > st.outlier_sigma * sd[lv])
            if bad.any():
                res2 = _estimate_camera(np.where(bad, np.nan, y[c]), lev, M, st)
                if res2 is not None:
                    mu_c, var_c = res2
        mu[c], var[c] = mu_c, var_c
    return ChannelModel(mu=mu, var=var, kind=kind, nu=nu)


@dataclass(frozen=True)
class ChannelTrack:
    """A channel that changes along a packet: ``models[j]`` holds for packet symbols
    ``starts[j] <= k < starts[j + 1]`` (the last one to the end; symbols before
    ``starts[0]`` use the first). An approaching car's LEDs brighten as 1/Z^2 -- about 2x
    within one 1.3 s packet at 40 km/h from 50 m -- and its spots grow and move across the
    ROI, so one model per packet no longer fits its end (docs/receiver.md)."""

    starts: tuple[int, ...]
    models: tuple[ChannelModel, ...]

    def __post_init__(self) -> None:
        if not self.models or len(self.starts) != len(self.models):
            raise ValueError("ChannelTrack: one start per model, at least one model")
        if any(b <= a for a, b in zip(self.starts[:-1], self.starts[1:])):
            raise ValueError(f"ChannelTrack: starts must increase, got {self.starts}")

    @classmethod
    def single(cls, model: ChannelModel) -> "ChannelTrack":
        """A track of one model, holding for the whole packet.

        Parameters
        ----------
        model : ChannelModel
            The channel.

        Returns
        -------
        ChannelTrack
            ``starts = (0,)``, ``models = (model,)``.
        """
        return cls((0,), (model,))

    @cached_property
    def tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stacked centroids, variances (J, C, N, M) and interpolation errors (J, C, N, M-1)."""
        return (np.stack([m.mu for m in self.models]), np.stack([m.var for m in self.models]),
                np.stack([m.interp_error for m in self.models]))

    def segment(self, k: np.ndarray) -> np.ndarray:
        """Index of the model holding for each packet symbol k.

        Parameters
        ----------
        k : ndarray
            Packet symbol indices, symbols.

        Returns
        -------
        ndarray of intp
            Indices into :attr:`models`, the shape of ``k`` (symbols before ``starts[0]`` get 0).
        """
        j = np.searchsorted(np.asarray(self.starts), np.asarray(k), side="right") - 1
        return np.clip(j, 0, len(self.models) - 1)
