"""The dissertation's results (SPEC section 5), as the evaluation report quotes them.

Only what the dissertation states in numbers or words is here; its figures' curves are not
tabulated in the text, so fig. 3.7 and fig. 3.8 are represented by the bounds the text gives.
"""

from __future__ import annotations

FIG_3_7_RANGING = {
    "dissertation": "mean absolute range error < 0.5 m out to 60 m (bicubic x3 + POC + sinc fit)",
    "poc": "about 0.8 m at 55-60 m (conventional POC, no interpolation)",
}
"""Fig. 3.7 (single LED, PWM-8, b = 0.6 m, 20-60 m, 5000 frames a point)."""

FIG_3_7_BOUND_M = {"dissertation": 0.5, "poc": 0.8}
"""The numbers of fig. 3.7's text: the bound for bicubic + POC, the level of plain POC at
55-60 m, m."""


def fig_3_8_ser(levels: int, distance_m: float) -> tuple[str, float | None]:
    """The dissertation's symbol error rate at a distance (fig. 3.8, single LED, b = 0.6 m):
    (text for the table, upper bound or None). OOK and PWM-8 are error-free to 55 m; PWM-8
    is below 6e-3 at 60 m; OOK at 60 m is not stated."""
    if levels not in (2, 8):
        return ("-", None)
    if distance_m <= 55.0 + 1e-9:
        return ("0", 0.0)
    if levels == 8 and abs(distance_m - 60.0) < 1e-9:
        return ("< 6e-3", 6e-3)
    return ("n/a", None)


TABLE_4_2_KBPS = {
    # (left f-number or None, right f-number or None, reception): (PWM-8, PWM-16)
    (None, 4.0, "single"): (74.29, 44.4),
    (None, 8.0, "single"): (80.71, 58.88),
    (None, 16.0, "single"): (58.78, 76.64),
    (4.0, None, "single"): (80.71, 58.88),
    (4.0, 4.0, "diversity"): (83.79, 98.33),
    (4.0, 8.0, "hdr"): (88.02, 88.25),
    (4.0, 16.0, "hdr"): (87.57, 105.17),
}
"""Table 4.2: the minimum over 10-50 m of the throughput (4.4), kbps, 8x8 array, b = 0.25 m.
(The f/4-left single-reception row repeats the f/8-right one in the dissertation.)"""

TABLE_4_2_ERROR_FREE_KBPS = {8: 88.2, 16: 117.6}
"""(4.4) with SER = 0 for 8x8 LEDs, F = 600, 653-symbol packets at 500 Hz."""


def table_4_2(left_f: float | None, right_f: float | None, reception: str, levels: int) -> float | None:
    """The dissertation's table 4.2 entry (kbps) for a reception mode, or None."""
    row = TABLE_4_2_KBPS.get((left_f, right_f, reception))
    if row is None or levels not in (8, 16):
        return None
    return row[0] if levels == 8 else row[1]


EARLIER_WORK = ("stereo ranging 0.5 m error at 20-60 m with 500 bps [69]; 0.1-1.5 m up to 100 m [57]; "
                "a simulation with 19.8 mm error at 30 m [62] (dissertation tables 1.1, 1.2)")
