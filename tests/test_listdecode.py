"""CRC-aided list decoding (iscd.decode.comms.listdecode): the order of the candidate sets,
the search on real air-interface packets, and the assembler's last resort."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from iscd.core.airinterface import AirInterface
from iscd.decode.comms import listdecode
from iscd.decode.comms.listdecode import flip_sets, list_decode


def _air(n_leds: int = 1, levels: int = 8) -> AirInterface:
    return AirInterface(levels=levels, n_leds=n_leds, training_symbols=40, data_symbols=600, idle_symbols=0)


def test_flip_sets_come_once_each_in_order_of_summed_cost() -> None:
    rng = np.random.default_rng(7)
    for T in (1, 2, 5, 9):
        c = np.sort(rng.exponential(5.0, T))
        if T == 9:
            c[3] = c[4]  # ties
        sets = list(flip_sets(c, 10_000))
        every = [s for k in range(1, T + 1) for s in itertools.combinations(range(T), k)]
        assert sorted(sets) == sorted(every)  # each non-empty set once
        sums = [float(c[list(s)].sum()) for s in sets]
        assert all(b >= a - 1e-12 for a, b in zip(sums, sums[1:]))  # never a larger sum first
        assert all(list(s) == sorted(s) for s in sets)
    assert len(list(flip_sets(np.arange(20.0), 37))) == 37
    assert list(flip_sets(np.array([]), 5)) == [] and list(flip_sets(np.ones(3), 0)) == []


def _noisy_decisions(air: AirInterface, wrong: int, rng: np.random.Generator, runner_is_truth: bool = True
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bytes]:
    """A real packet's data levels with ``wrong`` of them one level off: the wrong ones
    among the least reliable decisions (margins 0.5-1.5) with the truth as runner-up, the
    others margins 3-80 with a neighbouring runner-up."""
    payload = rng.integers(0, 256, air.payload_bytes, dtype=np.uint8).tobytes()
    sent = air.encode_data(payload).astype(np.uint8)
    M = air.levels
    F, N = sent.shape
    up = np.where(sent < M, sent + 1, sent - 1)
    runner = np.where(rng.random((F, N)) < 0.5, up, np.where(sent > 1, sent - 1, sent + 1)).astype(np.uint8)
    margins = rng.uniform(3.0, 80.0, (F, N))
    levels = sent.copy()
    idx = rng.choice(F * N, wrong, replace=False)
    flat_l, flat_r, flat_m = levels.reshape(-1), runner.reshape(-1), margins.reshape(-1)
    flat_l[idx] = up.reshape(-1)[idx]
    flat_r[idx] = sent.reshape(-1)[idx] if runner_is_truth else np.where(
        flat_l[idx] < M, flat_l[idx] + 1, flat_l[idx] - 1)
    flat_m[idx] = rng.uniform(0.5, 1.5, wrong)
    return levels, margins, runner, sent, payload


@pytest.mark.parametrize("n_leds, wrong", [(1, 1), (1, 3), (1, 5), (4, 2), (64, 4)])
def test_a_packet_a_few_weak_decisions_off_is_recovered_exactly(n_leds: int, wrong: int) -> None:
    """Real air-interface packets (1, 4 and 64 LEDs, PWM-8) with 1-5 decisions one level
    off, each among the least reliable and its runner-up the level sent: the CRC passes on
    the sent payload, with exactly those symbols changed; the input is left as it was."""
    rng = np.random.default_rng(100 + 10 * n_leds + wrong)
    air = _air(n_leds)
    levels, margins, runner, sent, payload = _noisy_decisions(air, wrong, rng)
    before = levels.copy()
    assert not air.decode_data(levels)[1]
    got = list_decode(air, levels, margins, runner)
    assert got is not None
    fixed, raw, flips, tried = got
    np.testing.assert_array_equal(fixed, sent)
    assert raw == payload and flips == wrong and 1 <= tried <= listdecode.LIST_CANDIDATES
    np.testing.assert_array_equal(levels, before)


def test_nothing_is_delivered_when_the_truth_is_not_on_the_list() -> None:
    """Wrong decisions whose runner-up is not the level sent, or too many to reach within the
    budget, or among reliable decisions beyond ``positions``: no candidate passes (None),
    after at most ``candidates`` CRC checks."""
    rng = np.random.default_rng(5)
    air = _air(1)
    levels, margins, runner, _, _ = _noisy_decisions(air, 2, rng, runner_is_truth=False)
    assert list_decode(air, levels, margins, runner) is None
    levels, margins, runner, _, _ = _noisy_decisions(air, 9, rng)  # 2^9 sets: beyond 256
    assert list_decode(air, levels, margins, runner, candidates=256) is None
    got = list_decode(air, levels, margins, runner, candidates=20_000)
    assert got is not None and got[2] == 9 and 256 < got[3] <= 20_000
    levels, margins, runner, sent, _ = _noisy_decisions(air, 1, rng)
    wrong = np.flatnonzero(levels.reshape(-1) != sent.reshape(-1))
    margins.reshape(-1)[wrong] = 1e3  # the wrong decision looks the most reliable
    assert list_decode(air, levels, margins, runner, positions=24) is None


def test_a_wrong_decision_past_the_24_least_reliable_is_in_reach() -> None:
    """The list is the likelihood order over every decision (``LIST_POSITIONS`` None): one
    wrong decision ranked 30th by margin -- confident, but 29 others are weaker still -- is
    found within the 256 candidates; with the depth cut of 24 positions (before session 28)
    it was not, whatever the budget."""
    rng = np.random.default_rng(28)
    air = _air(1)
    levels, margins, runner, sent, payload = _noisy_decisions(air, 1, rng)
    flat = margins.reshape(-1)
    wrong = int(np.flatnonzero(levels.reshape(-1) != sent.reshape(-1))[0])
    others = np.setdiff1d(np.arange(flat.size), [wrong])
    flat[others] = rng.uniform(40.0, 80.0, others.size)
    weak = rng.choice(others, 29, replace=False)
    flat[weak] = rng.uniform(12.0, 19.0, 29)  # 29 decisions weaker than the wrong one (any two: stronger)
    flat[wrong] = 20.0
    assert int((flat < flat[wrong]).sum()) == 29  # the wrong decision ranks 30th
    got = list_decode(air, levels, margins, runner)
    assert got is not None and got[1] == payload and got[2] == 1 and got[3] == 30
    assert list_decode(air, levels, margins, runner, positions=24, candidates=20_000) is None


def test_decisions_without_an_alternative_are_never_changed() -> None:
    air = _air(1)
    rng = np.random.default_rng(9)
    levels, margins, runner, _, _ = _noisy_decisions(air, 1, rng)
    assert list_decode(air, levels, np.full(levels.shape, np.inf), runner) is None
    assert list_decode(air, levels, margins, levels.copy()) is None


def test_shapes_are_checked() -> None:
    air = _air(1)
    z = np.ones((600, 1), np.uint8)
    with pytest.raises(ValueError, match=r"\(600, 1\)"):
        list_decode(air, z[:10], np.ones((10, 1)), z[:10])


def test_two_attempts_combine_where_they_disagree() -> None:
    """Per symbol the more confident attempt's level; where they disagree the margins'
    difference and the other level as the alternative; where they agree the chosen one's
    own margin and runner-up."""
    la = np.array([[1], [2], [3], [4]], np.uint8)
    lb = np.array([[1], [3], [3], [5]], np.uint8)
    ma = np.array([[5.0], [2.0], [9.0], [7.0]])
    mb = np.array([[6.0], [8.0], [1.0], [3.0]])
    ra = np.array([[2], [1], [4], [3]], np.uint8)
    rb = np.array([[8], [4], [2], [6]], np.uint8)
    lev, mar, run = listdecode.combine((la, ma, ra), (lb, mb, rb))
    np.testing.assert_array_equal(lev[:, 0], [1, 3, 3, 4])
    np.testing.assert_allclose(mar[:, 0], [6.0, 6.0, 9.0, 4.0])
    np.testing.assert_array_equal(run[:, 0], [8, 2, 4, 5])
    assert lev.dtype == run.dtype == np.uint8
    with pytest.raises(ValueError, match="one shape"):
        listdecode.combine((la, ma, ra), (lb[:2], mb[:2], rb[:2]))


def test_two_attempts_wrong_in_different_places_are_recovered_combined() -> None:
    """Two attempts at one real packet, each with 6 wrong symbols, none in common (each
    wrong decision weak, the other attempt sure there): neither alone is on its own list
    within 3 candidates, the combination is the sent packet itself."""
    rng = np.random.default_rng(21)
    air = _air(1)
    payload = rng.integers(0, 256, air.payload_bytes, dtype=np.uint8).tobytes()
    sent = air.encode_data(payload).astype(np.uint8)
    up = np.where(sent < 8, sent + 1, sent - 1).astype(np.uint8)
    idx = rng.choice(600, 12, replace=False)
    atts = []
    for part in (idx[:6], idx[6:]):
        lev, mar = sent.copy(), rng.uniform(10.0, 60.0, sent.shape)
        lev.reshape(-1)[part] = up.reshape(-1)[part]
        mar.reshape(-1)[part] = rng.uniform(1.0, 5.0, 6)
        atts.append((lev, mar, up.copy()))
    for a in atts:
        assert list_decode(air, *a, candidates=3) is None
    lev, mar, run = listdecode.combine(*atts)
    np.testing.assert_array_equal(lev, sent)
