"""CRC-aided list decoding of a failed packet: the decided levels with some of the least
reliable decisions set to their runner-up, tried in order of likelihood until one passes the
CRC (Chase's algorithm [1], the list ordered as in [2]).

A packet that every demodulation attempt failed often misses by a symbol or a few, each a
decision between two neighbouring levels that the noise tipped (a far, dim LED: one to ten
wrong symbols of 600, each one level off and among the least reliable decisions). The
decision's *margin* (:mod:`iscd.decode.comms.decide`: the cost gap to the runner-up, twice
the log-likelihood ratio of the two levels for the Gaussian model) says how much less
likely the runner-up is; for independent decisions the summed margins of a set of
symbols say how much less likely the packet with all of them changed is. So the sets of
the ``positions`` least reliable decisions (all of them by default) are enumerated in order
of their summed margin (a best-first search over the sorted margins: from a set whose largest member is i, the
set with i + 1 added and the set with i replaced by i + 1, which reaches every set once,
never before a set of smaller sum) and each is checked by the CRC, at most ``candidates``
of them.

Two attempts at the same packet (the first and the anchored one, :mod:`iscd.decode.comms.demod`)
that disagree on some symbols are first combined (:func:`combine`): per symbol the decision
of the larger margin, its reliability there the difference of the two margins and its
alternative the other attempt's level; the list then starts from that.

**Integrity.** Each candidate that is not the sent packet passes CRC-32 with probability
about 2^-32, so trying C candidates accepts a wrong payload with probability at most
C 2^-32 per failed packet (the assembler's at most five lists of 256: 3.0e-7; a delivered packet
says how many symbols were changed, ``list_flips``). Only air interface v1 packets are
list-decoded: v2 carries its own Reed-Solomon code, whose erasures already use the margins.

References
----------
[1] D. Chase, "A class of algorithms for decoding block codes with channel measurement
    information", IEEE Trans. Inf. Theory 18(1), 1972.
[2] M. P. C. Fossorier and S. Lin, "Soft-decision decoding of linear block codes based on
    ordered statistics", IEEE Trans. Inf. Theory 41(5), 1995.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator

import numpy as np

from iscd.core.airinterface import AirInterface
from iscd.decode.comms.demod import decode_data

LIST_DECODE = True
"""A held packet that every attempt failed, the anchored one too, is list-decoded
(:class:`~iscd.decode.comms.packets.PacketAssembler`); False: reported failed as it was."""

LIST_CANDIDATES = 256
"""Candidate packets tried beyond the one as decided (each one more 2^-32 chance that a
wrong payload passes the CRC)."""

LIST_POSITIONS: int | None = None
"""How many of the least reliable decisions may be set to their runner-up; None: any of them
(the list is then the ``candidates`` sets of least summed margin over all decisions, the
likelihood order itself). Past about ``candidates`` positions a bound changes little: a set
holding the k-th least reliable decision sums at least its margin, as the k sets of one
decision before it do each. Before session 28 the 24 least reliable: a depth cut, not an
integrity one (the candidates bound that), which left out a wrong decision ranked 26th that
was one flip from the sent packet after 43 candidates (1419451072, 100 km/h engine
vibration)."""


def flip_sets(costs: np.ndarray, most: int) -> Iterator[tuple[int, ...]]:
    """The non-empty sets of indices into ``costs`` in non-decreasing order of their summed
    cost, at most ``most`` of them.

    Parameters
    ----------
    costs : ndarray
        (T,) non-negative costs sorted ascending (the least reliable decisions' margins).
    most : int
        Largest number of sets to yield.

    Yields
    ------
    tuple of int
        Indices ascending, each set once.
    """
    T = int(costs.size)
    if T == 0 or most <= 0:
        return
    c = [float(v) for v in costs]
    heap: list[tuple[float, tuple[int, ...]]] = [(c[0], (0,))]
    given = 0
    while heap and given < most:
        s, sub = heapq.heappop(heap)
        yield sub
        given += 1
        i = sub[-1]
        if i + 1 < T:
            heapq.heappush(heap, (s + c[i + 1], sub + (i + 1,)))
            heapq.heappush(heap, (s - c[i] + c[i + 1], sub[:-1] + (i + 1,)))


def combine(a: tuple[np.ndarray, np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two attempts' decisions of one packet as one: per symbol the level of the larger
    margin (``a``'s on ties); where the two agree its margin and runner-up, where they
    disagree the margins' difference and the other attempt's level.

    Parameters
    ----------
    a, b : tuple of ndarray
        Each (levels, margins, runner_up), (F, N): levels 1..M, margins (cost gap to the
        runner-up), runner-up levels 1..M.

    Returns
    -------
    levels, margins, runner_up : ndarray
        (F, N) each, as :func:`list_decode` takes them (levels and runner-ups uint8).
    """
    la, ma, ra = a
    lb, mb, rb = b
    if not (la.shape == ma.shape == ra.shape == lb.shape == mb.shape == rb.shape):
        raise ValueError("combine: the two attempts' levels, margins and runner-ups must have one shape")
    take_b = mb > ma
    dis = la != lb
    levels = np.where(take_b, lb, la).astype(np.uint8)
    margins = np.where(dis, np.abs(ma - mb), np.where(take_b, mb, ma))
    runner = np.where(dis, np.where(take_b, la, lb), np.where(take_b, rb, ra)).astype(np.uint8)
    return levels, margins, runner


def list_decode(air: AirInterface, levels: np.ndarray, margins: np.ndarray, runner_up: np.ndarray,
                *, candidates: int = LIST_CANDIDATES, positions: int | None = LIST_POSITIONS
                ) -> tuple[np.ndarray, bytes, int, int] | None:
    """The most likely candidate packet, among the decided ``levels`` with sets of the
    ``positions`` least reliable decisions set to their runner-up, that passes the CRC.

    Parameters
    ----------
    air : AirInterface
        The packet's air interface (v1).
    levels : ndarray
        (F, N) decided data levels 1..M (uint8), which failed the CRC.
    margins : ndarray
        (F, N) decision margins (cost gap to the runner-up; inf: no alternative).
    runner_up : ndarray
        (F, N) the runner-up levels 1..M.
    candidates : int
        Most candidates tried (keyword-only).
    positions : int or None
        Decisions that may change: the least reliable ones (keyword-only; None: any).

    Returns
    -------
    (levels, payload, flips, tried) or None
        The candidate's levels (F, N) uint8, its payload bytes, how many symbols it changed
        and how many candidates were tried; None when none of them passed.

    Raises
    ------
    ValueError
        If the arrays' shapes do not match the air interface's data symbols.
    """
    shape = (air.data_symbols, air.n_leds)
    if levels.shape != shape or margins.shape != shape or runner_up.shape != shape:
        raise ValueError(f"list_decode: levels, margins and runner_up must be {shape} (F, N), "
                         f"got {levels.shape}, {margins.shape}, {runner_up.shape}")
    m = np.asarray(margins, dtype=np.float64).reshape(-1)
    alt = np.asarray(runner_up, dtype=np.uint8).reshape(-1)
    work = np.ascontiguousarray(levels, dtype=np.uint8).copy()
    flat = work.reshape(-1)
    usable = np.flatnonzero(np.isfinite(m) & (alt != flat))
    if usable.size == 0:
        return None
    order = usable[np.argsort(m[usable], kind="stable")[:positions]]  # ([:None]: all)
    costs = m[order]
    tried = 0
    for sub in flip_sets(costs, candidates):
        tried += 1
        idx = order[list(sub)]
        keep = flat[idx].copy()
        flat[idx] = alt[idx]
        raw, ok = decode_data(air, work)
        if ok:
            return work, raw, len(sub), tried
        flat[idx] = keep
    return None
