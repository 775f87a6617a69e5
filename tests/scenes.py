"""Randomized motion scenes for the following tests (issue 12): a scene's config drawn as
``iscd eval --suite motion --randomize`` draws it, and how far the receiver's followed
centres lie from the simulator's truth. Imported by the tests (``from scenes import ...``,
as ``fakes``)."""

from __future__ import annotations

from typing import Any

import numpy as np


def motion_scene(key: str, seed: int, model: str, background_motion: str = "whole", **tracking: Any):
    """The config of randomized scene ``seed`` of motion case ``key`` under vibration model
    ``model``, with ``[tracking]`` keys set as given. ``background_motion``: the scene's
    background moves by ``whole`` pixels (as every randomized scene did before session 36,
    when the scenes these tests pin were found) or by the exact ``subpixel`` shift."""
    from iscd.core.config import default_config
    from iscd.eval.suites import MOTION_CASES, motion_cfg

    case = next(c for c in MOTION_CASES if c.key == key)
    cfg, note = motion_cfg(default_config(), case, seed,
                           scene={"vibration_model": model, "background_motion": background_motion}, randomize=True)
    assert note.startswith("randomized")
    return cfg.with_keys("tracking", **tracking) if tracking else cfg


def following_errors(cfg, n: int, block: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(2, F) distance of the followed centres from the simulator's truth, px, over the frames
    the receiver followed (per camera), and (F,) the share of each of those frames' exposure
    the LED was on (truth). Frames 0 .. n - 1 in blocks of ``block`` (the daemon's 16)."""
    from iscd.decode.stream import StreamDecoder
    from iscd.eval.sweeps import ReceiverMode, _decoder_cfg
    from iscd.sim.scene import Scene

    sc = Scene(cfg)
    truth = sc.truth(np.arange(n))
    dec = StreamDecoder(_decoder_cfg(cfg, ReceiverMode("diversity", "both")))
    L = np.empty((block, sc.height, sc.width), np.uint8)
    R = np.empty_like(L)
    err: list[list[float]] = [[], []]
    on: list[float] = []
    for s in range(0, n, block):
        ids = np.arange(s, min(s + block, n))
        for i, k in enumerate(ids):
            sc.render_pair_into(int(k), L[i], R[i])
        dec.push(ids, ids / sc.fps, L[:ids.size], R[:ids.size])
        if dec.last_centres is not None and dec.last_centres[0].shape[0] == ids.size:
            for c, (u, v) in enumerate(((truth.u_left, truth.v_left), (truth.u_right, truth.v_right))):
                got = dec.last_centres[c][:, 0, :]
                err[c].extend(np.hypot(got[:, 0] - np.ravel(u)[ids], got[:, 1] - np.ravel(v)[ids]))
            on.extend(np.asarray(truth.on_fraction)[ids, 0])
    dec.close()
    return np.array(err), np.array(on)


def assert_delivered_only_with(cfg_with, cfg_without, what: str) -> None:
    """Two packets of a randomized scene in the daemon's blocks of 16, decoded by the default
    receiver with a setting (``cfg_with``) and without it: bit-exact with it (nothing
    undetected, nothing spurious), and at least one of the two lost without it (62001's
    2103417577 under bumps loses both since session 34's receiver)."""
    from iscd.eval.sweeps import ReceiverMode, run_comms

    mode = ReceiverMode("diversity", "both")
    (res,) = run_comms(cfg_with, [mode], 2, block=16)
    (off,) = run_comms(cfg_without, [mode], 2, block=16)
    print(f"with {what}: exact {res.exact}/{res.packets_sent}, errors {res.symbol_errors}; "
          f"without: exact {off.exact}, errors {off.symbol_errors}")
    assert res.found == res.packets_sent == 2 and res.exact == 2 and res.symbol_errors == 0
    assert res.undetected == 0 and res.spurious_crc_ok == 0
    assert off.exact <= 1 and off.symbol_errors > 0
