"""Reed-Solomon over GF(256) and the byte interleaver of air interface v2 (pure functions).

The code is the classic one of CCSDS / DVB / ``reedsolo``'s defaults: GF(2^8) with the
primitive polynomial x^8 + x^4 + x^3 + x^2 + 1 (0x11d), generator alpha = 2, first
consecutive root alpha^0; the generator polynomial of ``nsym`` parity bytes is
g(x) = prod_{i=0}^{nsym-1} (x - alpha^i). Codewords are systematic: the data bytes, then the
``nsym`` parity bytes (the remainder of data(x) x^nsym mod g(x)); a codeword shorter than
255 bytes is the shortened code (leading zeros that are not sent). ``tests/test_fec.py``
checks the encoder byte for byte against ``reedsolo`` (the pure-Python reference).

Decoding corrects e errors and f erasures (positions known to be unreliable) whenever
2e + f <= nsym (the Singleton bound of an MDS code): syndromes, the Berlekamp-Massey
algorithm started from the erasure locator, Chien search, Forney's formula, and a final
syndrome check of the corrected word. A word beyond that bound is either reported failed
(``-1``) or corrected to another codeword; the CRC-32 over the whole payload
(:mod:`iscd.core.airinterface_v2`) catches the latter.

The kernels are compiled (:func:`iscd.core.jit.njit`) and work on a batch of codewords at
once (one packet's), ``benchmarks/bench_fec.py`` times them beside ``reedsolo`` /
``creedsolo`` and ``galois``.

Interleaver (:func:`interleave_order`): codeword c's byte t goes to stream position
``t * n_cw + c`` (codewords written as rows, read out by columns, the rows of different
lengths skipped where they have ended), so consecutive stream bytes -- one symbol time of
all LEDs, a burst of symbol times -- belong to different codewords, and one LED's bytes
(a stride of N log2(M) / 8 bytes) visit every codeword when n_cw is coprime to
N log2(M) (:func:`codeword_count` makes it so).
"""

from __future__ import annotations

import math

import numpy as np

from iscd.core.jit import njit

PRIM = 0x11D
"""GF(2^8) primitive polynomial x^8 + x^4 + x^3 + x^2 + 1."""
N_MAX = 255
"""Longest codeword, bytes."""


def _tables() -> tuple[np.ndarray, np.ndarray]:
    exp = np.zeros(512, np.int64)
    log = np.zeros(256, np.int64)
    x = 1
    for i in range(255):
        exp[i] = x
        log[x] = i
        x <<= 1
        if x & 0x100:
            x ^= PRIM
    exp[255:510] = exp[:255]
    return exp, log


GF_EXP, GF_LOG = _tables()
"""alpha^i for i in 0..509 (twice round, so that log a + log b needs no modulo) and the
discrete logarithm of 1..255 (log 0 unused)."""


def generator_poly(nsym: int) -> np.ndarray:
    """g(x) = prod_{i<nsym} (x - alpha^i), coefficients highest degree first (g[0] = 1).

    Parameters
    ----------
    nsym : int
        Parity bytes, 1..254.

    Returns
    -------
    ndarray
        (nsym + 1,) int64 coefficients.
    """
    g = np.array([1], np.int64)
    for i in range(nsym):
        nxt = np.zeros(g.size + 1, np.int64)
        nxt[:-1] = g
        a = GF_EXP[i]
        for j in range(g.size):  # + g[j] * alpha^i in the next lower degree
            if g[j]:
                nxt[j + 1] ^= GF_EXP[GF_LOG[g[j]] + GF_LOG[a]]
        g = nxt
    return g


def _warm_encode() -> tuple:
    return (np.zeros((2, 8), np.uint8), np.array([8, 6], np.int64), generator_poly(4), GF_EXP, GF_LOG)


@njit(warm=_warm_encode)
def _encode_batch(data: np.ndarray, k: np.ndarray, gen: np.ndarray, exp: np.ndarray,
                  log: np.ndarray) -> np.ndarray:
    """Parity bytes (n_cw, nsym) of the rows of data (n_cw, kmax) uint8, row c's first k[c]
    bytes: the remainder of data(x) x^nsym mod g(x) (LFSR division)."""
    n_cw = data.shape[0]
    nsym = gen.size - 1
    par = np.zeros((n_cw, nsym), np.uint8)
    lg = np.empty(nsym, np.int64)
    for j in range(nsym):
        lg[j] = log[gen[j + 1]] if gen[j + 1] else -1
    reg = np.zeros(nsym, np.int64)
    for c in range(n_cw):
        reg[:] = 0
        for i in range(k[c]):
            fb = np.int64(data[c, i]) ^ reg[0]
            for j in range(nsym - 1):
                reg[j] = reg[j + 1]
            reg[nsym - 1] = 0
            if fb:
                lf = log[fb]
                for j in range(nsym):
                    if lg[j] >= 0:
                        reg[j] ^= exp[lf + lg[j]]
        for j in range(nsym):
            par[c, j] = reg[j]
    return par


def _warm_decode() -> tuple:
    return (np.zeros((2, 12), np.uint8), np.array([12, 10], np.int64), np.zeros((2, 12), np.bool_),
            4, GF_EXP, GF_LOG)


@njit(warm=lambda: (3, 5, GF_EXP, GF_LOG))
def _gmul(a: int, b: int, exp: np.ndarray, log: np.ndarray) -> int:
    if a == 0 or b == 0:
        return 0
    return exp[log[a] + log[b]]


@njit(warm=lambda: (3, 5, GF_EXP, GF_LOG))
def _gdiv(a: int, b: int, exp: np.ndarray, log: np.ndarray) -> int:
    if a == 0:
        return 0
    return exp[log[a] + 255 - log[b]]


@njit(warm=_warm_decode)
def _decode_batch(words: np.ndarray, n: np.ndarray, erase: np.ndarray, nsym: int,
                  exp: np.ndarray, log: np.ndarray) -> np.ndarray:
    """Correct the rows of words (n_cw, nmax) uint8 in place (row c's first n[c] bytes, a
    codeword of nsym parity bytes, erasures where erase[c] is True); returns per row the
    number of bytes changed, or -1 where the row could not be decoded (left as received)."""
    n_cw = words.shape[0]
    out = np.zeros(n_cw, np.int64)
    S = np.zeros(nsym, np.int64)
    lam = np.zeros(nsym + 1, np.int64)
    B = np.zeros(nsym + 2, np.int64)
    T = np.zeros(nsym + 1, np.int64)
    om = np.zeros(nsym, np.int64)
    pos = np.zeros(nsym + 1, np.int64)
    for c in range(n_cw):
        nc = n[c]
        # syndromes S_i = r(alpha^i), Horner from the first (highest) byte
        zero = True
        for i in range(nsym):
            s = 0
            if i == 0:
                for j in range(nc):
                    s ^= np.int64(words[c, j])
            else:
                for j in range(nc):
                    s = (exp[log[s] + i] if s else 0) ^ np.int64(words[c, j])
            S[i] = s
            if s:
                zero = False
        f = 0
        for j in range(nc):
            if erase[c, j]:
                f += 1
        if zero:
            continue
        if f > nsym:
            out[c] = -1
            continue
        # erasure locator Gamma(x) = prod (1 - X_e x), X_e = alpha^(nc - 1 - j)
        lam[:] = 0
        lam[0] = 1
        deg = 0
        for j in range(nc):
            if erase[c, j]:
                X = exp[nc - 1 - j]
                for d in range(deg + 1, 0, -1):
                    lam[d] ^= _gmul(lam[d - 1], X, exp, log)
                deg += 1
        B[:] = 0
        B[:nsym + 1] = lam
        L = f
        m = 1
        bb = 1
        for r in range(f, nsym):
            dlt = S[r]
            for i in range(1, min(L, r) + 1):
                if lam[i] and S[r - i]:
                    dlt ^= exp[log[lam[i]] + log[S[r - i]]]
            if dlt == 0:
                m += 1
                continue
            coef = _gdiv(dlt, bb, exp, log)
            if 2 * L <= r + f:
                T[:] = lam
                for i in range(nsym + 1 - m):
                    if B[i]:
                        lam[i + m] ^= _gmul(coef, B[i], exp, log)
                L = r + 1 + f - L
                B[:nsym + 1] = T
                bb = dlt
                m = 1
            else:
                for i in range(nsym + 1 - m):
                    if B[i]:
                        lam[i + m] ^= _gmul(coef, B[i], exp, log)
                m += 1
        if L > nsym or 2 * (L - f) + f > nsym:
            out[c] = -1
            continue
        dl = 0
        for i in range(nsym + 1):
            if lam[i]:
                dl = i
        if dl != L:
            out[c] = -1
            continue
        # Chien search over the sent positions: Lambda(X_j^-1) == 0
        nr = 0
        for j in range(nc):
            inv = (255 - (nc - 1 - j)) % 255
            v = lam[0]
            for i in range(1, L + 1):
                if lam[i]:
                    v ^= exp[log[lam[i]] + (inv * i) % 255]
            if v == 0:
                if nr == L:
                    nr += 1
                    break
                pos[nr] = j
                nr += 1
        if nr != L:
            out[c] = -1
            continue
        # Omega(x) = S(x) Lambda(x) mod x^nsym; e_j = X_j Omega(X_j^-1) / Lambda'(X_j^-1)
        for i in range(nsym):
            o = 0
            for t in range(min(i, L) + 1):
                if lam[t] and S[i - t]:
                    o ^= exp[log[lam[t]] + log[S[i - t]]]
            om[i] = o
        changed = 0
        ok = True
        for q in range(nr):
            j = pos[q]
            xp = nc - 1 - j
            inv = (255 - xp) % 255
            num = 0
            for i in range(nsym):
                if om[i]:
                    num ^= exp[log[om[i]] + (inv * i) % 255]
            den = 0
            for i in range(1, L + 1, 2):
                if lam[i]:
                    den ^= exp[log[lam[i]] + (inv * (i - 1)) % 255]
            if den == 0:
                ok = False
                break
            if num:
                ev = exp[(log[num] + xp + 255 - log[den]) % 255]
                words[c, j] = np.uint8(np.int64(words[c, j]) ^ ev)
                changed += 1
        if ok:  # the corrected word must be a codeword
            for i in range(nsym):
                s = 0
                for j in range(nc):
                    s = (exp[log[s] + i] if s else 0) ^ np.int64(words[c, j])
                if s:
                    ok = False
                    break
        if not ok:  # (the caller restores the word as received)
            out[c] = -1
            continue
        out[c] = changed
    return out


class RSCode:
    """A Reed-Solomon code over GF(256) with ``nsym`` parity bytes per codeword (t =
    nsym / 2 errors or nsym erasures), codewords up to 255 bytes (shortened below)."""

    def __init__(self, nsym: int) -> None:
        if not 1 <= nsym <= 254:
            raise ValueError(f"nsym must be in 1..254, got {nsym}")
        self.nsym = int(nsym)
        self.gen = generator_poly(self.nsym)

    def encode(self, data: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Parity of each row.

        Parameters
        ----------
        data : ndarray
            (n_cw, kmax) uint8; row c's data are its first ``k[c]`` bytes.
        k : ndarray
            (n_cw,) data bytes per codeword, each <= 255 - nsym.

        Returns
        -------
        ndarray
            (n_cw, nsym) uint8 parity bytes (sent after the data).
        """
        k = np.asarray(k, np.int64)
        if k.size and (k.max() > N_MAX - self.nsym or k.min() < 0 or k.max() > data.shape[1]):
            raise ValueError("data bytes per codeword out of range")
        return _encode_batch(np.ascontiguousarray(data, np.uint8), k, self.gen, GF_EXP, GF_LOG)

    def decode(self, words: np.ndarray, n: np.ndarray, erase: np.ndarray | None = None) -> np.ndarray:
        """Correct codewords in place.

        Parameters
        ----------
        words : ndarray
            (n_cw, nmax) uint8 received codewords (row c's first ``n[c]`` bytes: data then
            parity); corrected in place (a row that fails is restored as received).
        n : ndarray
            (n_cw,) codeword lengths, bytes, nsym + 1 .. 255.
        erase : ndarray, optional
            (n_cw, nmax) bool: bytes known to be unreliable (erasures).

        Returns
        -------
        ndarray
            (n_cw,) int64: bytes corrected per codeword, -1 where it failed (more than
            2e + f <= nsym allows, detected).
        """
        n = np.asarray(n, np.int64)
        if words.dtype != np.uint8 or not words.flags.c_contiguous:
            raise ValueError("words must be a C-contiguous uint8 array")
        if n.size and (n.max() > min(N_MAX, words.shape[1]) or n.min() <= self.nsym):
            raise ValueError("codeword lengths out of range")
        er = np.zeros(words.shape, np.bool_) if erase is None else np.ascontiguousarray(erase, np.bool_)
        keep = words.copy()
        res = _decode_batch(words, n, er, self.nsym, GF_EXP, GF_LOG)
        bad = res < 0
        if bad.any():
            words[bad] = keep[bad]
        return res


def codeword_count(data_bytes: int, k_max: int, stride: int) -> int:
    """Codewords for ``data_bytes`` bytes of at most ``k_max`` data bytes each: the fewest,
    made coprime with ``stride`` (the bits of one symbol time of all LEDs) so that one
    LED's bytes visit every codeword (module docstring).

    Parameters
    ----------
    data_bytes : int
        Payload + CRC bytes.
    k_max : int
        Data bytes per codeword at most (255 - nsym).
    stride : int
        N log2(M), bits per symbol time.

    Returns
    -------
    int
        The number of codewords (>= 1).
    """
    c = max(1, -(-data_bytes // k_max))
    while math.gcd(c, stride) != 1:
        c += 1
    return c


def split_lengths(data_bytes: int, n_cw: int) -> np.ndarray:
    """Data bytes of each of n_cw codewords: as equal as can be, the longer first."""
    base, extra = divmod(data_bytes, n_cw)
    return np.array([base + 1] * extra + [base] * (n_cw - extra), np.int64)


def interleave_order(lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each stream byte comes from: the codeword and the byte within it.

    Parameters
    ----------
    lengths : ndarray
        (n_cw,) codeword lengths, bytes (data + parity).

    Returns
    -------
    ndarray, ndarray
        (sum(lengths),) codeword index and byte index of stream byte s: by columns,
        ``t * n_cw + c`` while every codeword still has byte t.
    """
    lengths = np.asarray(lengths, np.int64)
    n_cw = lengths.size
    nmax = int(lengths.max()) if n_cw else 0
    t, c = np.meshgrid(np.arange(nmax), np.arange(n_cw), indexing="ij")  # column-major read
    keep = t < lengths[c]
    return c[keep], t[keep]
