"""Reed-Solomon over GF(256) (iscd.core.fec): the encoder byte for byte against reedsolo
(the pure-Python reference, same field, generator and first root), errors and erasures
corrected exactly up to 2e + f <= nsym, beyond it never a silent wrong 'success' that is
not a codeword, and the interleaver's spreading."""

from __future__ import annotations

import numpy as np
import pytest
from fuzzing import fuzz
from hypothesis import given
from hypothesis import strategies as st

from iscd.core import fec

reedsolo = pytest.importorskip("reedsolo")


def _codeword(rng: np.random.Generator, nsym: int, k: int) -> np.ndarray:
    data = rng.integers(0, 256, (1, k), dtype=np.uint8)
    return np.ascontiguousarray(np.concatenate([data, fec.RSCode(nsym).encode(data, np.array([k]))], 1))


@pytest.mark.parametrize("nsym", [2, 16, 32, 64])
def test_encoder_matches_reedsolo(nsym: int) -> None:
    rng = np.random.default_rng(nsym)
    ref = reedsolo.RSCodec(nsym, nsize=255)
    for k in (1, 7, 100, 255 - nsym):
        cw = _codeword(rng, nsym, k)
        assert bytes(ref.encode(bytearray(cw[0, :k].tobytes()))) == cw[0].tobytes()


def test_generator_roots() -> None:
    """g(alpha^i) = 0 for i < nsym, g(alpha^nsym) != 0."""
    g = fec.generator_poly(16)

    def ev(x_log: int) -> int:
        acc = 0
        for c in g:
            acc = (fec.GF_EXP[fec.GF_LOG[acc] + x_log] if acc else 0) ^ int(c)
        return acc

    assert all(ev(i) == 0 for i in range(16)) and ev(16) != 0


@fuzz(150)
@given(st.sampled_from([2, 8, 16, 32, 64]), st.integers(1, 253), st.data())
def test_errors_and_erasures_up_to_the_limit(nsym: int, k: int, data: st.DataObject) -> None:
    k = min(k, 255 - nsym)
    n = k + nsym
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    f = data.draw(st.integers(0, min(nsym, n)))
    e = min((nsym - f) // 2, n - f)
    cw = _codeword(rng, nsym, k)
    w = cw.copy()
    where = rng.choice(n, e + f, replace=False)
    w[0, where[:e]] ^= rng.integers(1, 256, e).astype(np.uint8)  # errors: always wrong
    w[0, where[e:]] = rng.integers(0, 256, f).astype(np.uint8)  # erasures: any value
    er = np.zeros(w.shape, bool)
    er[0, where[e:]] = True
    res = fec.RSCode(nsym).decode(w, np.array([n]), er)
    assert res[0] >= 0 and np.array_equal(w, cw)
    assert res[0] <= e + f


@fuzz(100)
@given(st.sampled_from([8, 16, 32]), st.data())
def test_one_past_the_limit_fails_or_is_a_codeword(nsym: int, data: st.DataObject) -> None:
    """2e + f = nsym + 1 or 2: reported failed (word left as received), or corrected to a
    codeword (the CRC-32 of the packet must catch that one)."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n = 255
    f = data.draw(st.integers(0, nsym))
    e = (nsym - f) // 2 + 1
    cw = _codeword(rng, nsym, n - nsym)
    w = cw.copy()
    where = rng.choice(n, e + f, replace=False)
    w[0, where] ^= rng.integers(1, 256, e + f).astype(np.uint8)
    er = np.zeros(w.shape, bool)
    er[0, where[e:]] = True
    received = w.copy()
    res = fec.RSCode(nsym).decode(w, np.array([n]), er)
    if res[0] < 0:
        assert np.array_equal(w, received)
    else:  # a codeword: decoding it again changes nothing
        again = w.copy()
        assert fec.RSCode(nsym).decode(again, np.array([n]))[0] == 0 and not np.array_equal(w, cw)


def test_too_many_erasures_fail() -> None:
    cw = _codeword(np.random.default_rng(1), 8, 50)
    er = np.zeros(cw.shape, bool)
    er[0, :9] = True
    w = cw.copy()
    w[0, 0] ^= 1
    assert fec.RSCode(8).decode(w, np.array([58]), er)[0] == -1


def test_batch_rows_are_independent() -> None:
    rng = np.random.default_rng(3)
    rows = [_codeword(rng, 16, 200)[0] for _ in range(5)]
    cw = np.ascontiguousarray(np.stack(rows))
    w = cw.copy()
    w[1, :8] ^= 0x5A  # at the limit
    w[3, :9] ^= 0x5A  # past it
    res = fec.RSCode(16).decode(w, np.full(5, 216))
    assert res[0] == res[2] == res[4] == 0 and res[1] == 8
    assert np.array_equal(w[[0, 1, 2, 4]], cw[[0, 1, 2, 4]])


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        fec.RSCode(0)
    with pytest.raises(ValueError):
        fec.RSCode(16).decode(np.zeros((1, 300), np.uint8), np.array([300]))
    with pytest.raises(ValueError):
        fec.RSCode(16).encode(np.zeros((1, 250), np.uint8), np.array([250]))


def test_interleaver_spreads_rows_and_columns() -> None:
    """Stream bytes of one symbol time (32 bytes of an 8x8 PWM-16 array) hit 32 codewords;
    one LED's bytes (every 32nd) visit every codeword about equally."""
    n_cw = fec.codeword_count(16736, 223, 64 * 4)
    assert np.gcd(n_cw, 256) == 1
    lengths = fec.split_lengths(16736, n_cw) + 32
    cw, pos = fec.interleave_order(lengths)
    assert cw.size == lengths.sum() and len(set(zip(cw.tolist(), pos.tolist()))) == cw.size
    row = cw[320:352]
    assert len(set(row.tolist())) == 32
    counts = np.bincount(cw[5::32], minlength=n_cw)
    assert counts.min() >= counts.max() - 2 and counts.max() <= 9
