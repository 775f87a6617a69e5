"""iscd.eval.phaselight: a clipped spot's light depends on its sub-pixel phase (docs/eval.md,
session 32); taking that dependence out of each level's light, fitted on known sub-pixel
positions, leaves the noise alone -- and on a randomized scene whose +true positions
luminance loses both packets, fitted on one demodulation's own decisions, delivers both."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.eval.phaselight import main, phase_features, run, take_out_phase


def _synthetic(n: int = 2400, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Light of 8 levels with a slow trend, each level's own phase response (amplitude
    growing with the level) to a spot drifting 0.013 px a frame in x and vibrating in y,
    and 0.1 DN of noise: (light, clean light (no phase part), labels, x, y)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=np.float64)
    labels = rng.integers(1, 9, n)
    x = 200.0 - 0.013 * t
    y = 255.0 + 0.4 * np.sin(2 * np.pi * t / 37.0)
    f = phase_features(x, y)
    amp = np.stack([0.3 * labels, -0.2 * labels, 0.1 * labels, 0.05 * labels], 1)
    base = 10.0 * labels * (1.0 + 2e-4 * t) + rng.normal(0.0, 0.1, n)
    return base + (amp * f).sum(1), base, labels, x, y


def test_the_phase_part_is_taken_out_to_the_noise() -> None:
    light, base, labels, x, y = _synthetic()
    use = np.ones(light.size, bool)
    use[::7] = False  # frames left alone (e.g. straddles)
    light[5] = np.nan
    out = take_out_phase(light, labels, use, phase_features(x, y), window=400)
    fit = use & np.isfinite(light)
    assert np.std((light - base)[fit]) > 1.0  # the phase part before
    assert np.std((out - base)[fit]) < 0.05  # after: what is left is the fit's own error
    assert np.array_equal(out[~use], light[~use]) and np.isnan(out[5])
    with pytest.raises(ValueError, match="rows"):
        take_out_phase(light[:-1], labels, use, phase_features(x, y))
    with pytest.raises(ValueError, match="min_frames"):
        take_out_phase(light, labels, use, phase_features(x, y), min_frames=5)


def test_own_decisions_suffice_on_a_randomized_scene() -> None:
    """Set 72001's 134326035 (40 km/h, 0.5 px, smooth vibration): the +true positions
    luminance loses both packets to the squeezed top levels; with the phase taken out,
    fitted on its own decisions (tens of them wrong), both are delivered. (With one LED's
    window scaled as session 32 measured it: ``growth_from_block = false``.)"""
    r = run("1led-40kmh-0.5px", 134326035, "smooth", tracking={"growth_from_block": False})
    assert r["wrong_labels"] > 0
    assert not all(ok for ok, _ in r["before"].values()), r
    assert len(r["phase taken out"]) == 2 and all(ok for ok, _ in r["phase taken out"].values()), r


def test_the_receivers_own_luminance_and_followed_centres() -> None:
    """The same scene as the receiver measured it (its luminance, its followed centres): the
    receiver loses both packets; with the phase taken out the second is delivered."""
    r = run("1led-40kmh-0.5px", 134326035, "smooth", source="receiver", tracking={"growth_from_block": False})
    assert r["wrong_labels"] > 0
    assert len(r["before"]) == 2 and not any(ok for ok, _ in r["before"].values()), r
    assert r["phase taken out"][1][0], r


def test_bad_input_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for argv, what in ((["8x8-40kmh-0.3px", "1", "smooth"], "not a one-LED motion case"),
                       (["1led-40kmh-0.5px", "1", "smooth", "--labels", "oracle"], "labels"),
                       (["1led-40kmh-0.5px", "1", "smooth", "--window", "3"], "window"),
                       (["1led-40kmh-0.5px", "1", "smooth", "--source", "genie"], "source"),
                       (["1led-40kmh-0.5px", "1", "smooth", "--centre-noise", "inf"], "centre noise"),
                       (["1led-40kmh-0.5px", "-5", "smooth"], "seed")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("phaselight: ") and what in err and "\n" not in err, err
