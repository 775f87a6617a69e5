"""iscd.eval.levelnoise: each PWM level's noise at the true LED centres with parts of the
physics switched off (docs/eval.md, session 32): with nothing moving the top levels are as
clean as the bottom ones; the approach alone, which moves the right camera's clipped spot
over its pixel grid with the disparity, makes them noisy there and not in the left camera,
whose spot stays nearly put. Bad input is one line and exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from iscd.eval.levelnoise import main, measure, scene_config

STILL = ("approach", "vibration", "lateral", "texture")


def test_the_moving_clipped_spot_makes_the_top_levels_noisy() -> None:
    still = measure(scene_config("1led-40kmh-0.5px", 285800105, "engine", STILL), 1300)
    approach = measure(scene_config("1led-40kmh-0.5px", 285800105, "engine", STILL[1:]), 1300)
    assert still.z_m[0] == pytest.approx(still.z_m[1]) and approach.z_m[1] < approach.z_m[0] - 5.0
    assert approach.light.shape == (2, 1300) and approach.level.shape == approach.clean.shape == (1300,)
    # nothing moving: every level within 0.5 % of the range, neighbours > 10 noise widths apart
    assert np.all(still.noise_pct < 0.5), still.noise_pct
    assert np.nanmin(still.d_prime) > 10.0, still.d_prime
    # the approach alone: the right camera's top levels (its spot drifts with the disparity)
    # several times noisier than when still and than its own bottom level; the left's not
    right, left = approach.noise_pct[1], approach.noise_pct[0]
    assert right[-1] > 3.0 * still.noise_pct[1, -1] and right[-1] > 3.0 * right[0], approach.noise_pct
    assert left[-1] < 0.5, approach.noise_pct
    assert np.nanmin(approach.d_prime[1]) < 0.5 * np.nanmin(still.d_prime[1])


def test_bad_input_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for argv, what in ((["--off", "bogus"], "unknown part"), (["--case", "8x8-40kmh-0.3px"], "one LED only"),
                       (["--case", "nope"], "unknown case"), (["--frames", "100"], "fewer than two bins"),
                       (["--sigma", "nan"], "sigma"), (["--sigma", "inf"], "sigma")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("levelnoise: ") and what in err and "\n" not in err, err
    with pytest.raises(ValueError, match="one LED only"):
        scene_config("8x8-40kmh-0.3px", 1)
