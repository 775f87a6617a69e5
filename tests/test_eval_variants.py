"""python -m iscd.eval.variants: randomized scenes per case, variants on the same frames."""

from __future__ import annotations

from iscd.eval import variants


def test_scene_configs_are_drawn_per_case_and_seed_and_keep_the_motion() -> None:
    a = variants.scene_config("a40", 1)
    assert a == variants.scene_config("a40", 1)
    b = variants.scene_config("a40v5", 1)
    assert a.scene.speed_mps == 11.1 and a.scene.vibration_px == 0.3 and b.scene.vibration_px == 0.5
    assert a.scene.randomized_seed != b.scene.randomized_seed  # cases never share a draw
    assert a.transmitter.n_leds == 1 and a.scene.distractors == []


def test_bad_arguments_are_one_line_and_exit_2(capsys) -> None:
    assert variants.main(["--cases", "nope"]) == 2
    assert variants.main(["--seeds", "x"]) == 2
    assert variants.main(["--block", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("variants:") for line in err)


def test_a_still_scene_decodes_with_every_variant() -> None:
    cfg = variants.scene_config("still45", 4)
    res = variants.run_scene(cfg, ["default", "background"], packets=1)
    assert set(res) == {"default", "background"}
    for ok, ser in res.values():
        assert ok == 1 and ser == 0.0
