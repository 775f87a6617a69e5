"""Exact integration of the PWM transmitter's on-state over camera exposure windows.

Transmitter timing (SPEC section 3): the LED runs on its own clock

    t_led = (t_cam - phase_s) * (1 + drift_ppm * 1e-6)                      [s]

Symbol k covers t_led in [k*T, (k+1)*T), T = 1/symbol_rate_hz. Within a symbol the PWM
carrier (frequency f_pwm, its period aligned to the symbol start) is on for the first
``duty / f_pwm`` of each carrier period, duty = (s - 1)/(M - 1) (dissertation fig. 3.2).
Before symbol 0 the LED is dark (level 1).

The on-time integrated by an exposure window [a, b] (camera clock) is
``(G(t_led(b)) - G(t_led(a))) / (1 + drift)``, where G is the cumulative on-time on the
LED clock (:func:`cumulative_on_time`). Everything is exact (no sampling of the carrier)
and vectorized over frames x LEDs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LedClock:
    """The transmitter's clock relative to the camera clock.

    symbol_period_s: T = 1/f_sym, s.  pwm_hz: carrier frequency f_pwm, Hz.
    phase_s: camera time at which LED symbol 0 starts, s.  drift_ppm: LED clock rate error, ppm.
    """

    symbol_period_s: float
    pwm_hz: float
    phase_s: float = 0.0
    drift_ppm: float = 0.0

    @property
    def rate(self) -> float:
        """d t_led / d t_cam = 1 + drift_ppm * 1e-6."""
        return 1.0 + self.drift_ppm * 1e-6

    def led_time(self, t_cam: np.ndarray | float) -> np.ndarray:
        """LED clock time (s) of camera time ``t_cam`` (s).

        Parameters
        ----------
        t_cam : float or ndarray
            Camera clock time, s.

        Returns
        -------
        ndarray of float64
            t_led = (t_cam - phase_s) (1 + drift_ppm 1e-6), s, the shape of ``t_cam``.

        References
        ----------
        SPEC section 3.
        """
        return (np.asarray(t_cam, dtype=np.float64) - self.phase_s) * self.rate

    def cam_time(self, t_led: np.ndarray | float) -> np.ndarray:
        """Camera time (s) of LED clock time ``t_led`` (s).

        Parameters
        ----------
        t_led : float or ndarray
            LED clock time, s.

        Returns
        -------
        ndarray of float64
            Camera clock time, s, the shape of ``t_led``.
        """
        return np.asarray(t_led, dtype=np.float64) / self.rate + self.phase_s

    def symbol_start_cam(self, k: np.ndarray | int) -> np.ndarray:
        """Camera time (s) at which LED symbol ``k`` starts.

        Parameters
        ----------
        k : int or ndarray
            Symbol indices (LED clock; symbol k starts at t_led = k T).

        Returns
        -------
        ndarray of float64
            Camera clock time, s, the shape of ``k``.
        """
        return self.cam_time(np.asarray(k, dtype=np.float64) * self.symbol_period_s)


def partial_on_time(tau: np.ndarray, duty: np.ndarray, pwm_hz: float) -> np.ndarray:
    """On-time (s) of the first ``tau`` s of a symbol with PWM duty ``duty`` (0..1).

    The carrier period 1/f_pwm starts at the symbol start; in each period the LED is on
    for the first duty/f_pwm: ``floor(tau*f)*d/f + min(frac(tau*f), d)/f``.

    Parameters
    ----------
    tau : ndarray
        Time since the symbol start, s (LED clock), 0 <= tau <= T.
    duty : ndarray
        PWM duty (s - 1)/(M - 1), 0..1; broadcasts with ``tau``.
    pwm_hz : float
        Carrier frequency f_pwm, Hz.

    Returns
    -------
    ndarray of float64
        On-time, s (LED clock), the broadcast shape of ``tau`` and ``duty``.

    References
    ----------
    SPEC section 3; dissertation fig. 3.2.
    """
    x = np.asarray(tau, dtype=np.float64) * pwm_hz
    whole = np.floor(x)
    return (whole * duty + np.minimum(x - whole, duty)) / pwm_hz


def cumulative_on_time(t_led: np.ndarray, duties: np.ndarray, first_symbol: int,
                       clock: LedClock, cum: np.ndarray | None = None) -> np.ndarray:
    """G(t_led): on-time (s, LED clock) from ``first_symbol``'s start to ``t_led``.

    Parameters
    ----------
    t_led : ndarray
        (F,) LED clock times, s. Must lie in [first_symbol*T, (first_symbol + n_sym)*T]
        (a time exactly at the end is allowed).
    duties : ndarray
        (n_sym, N) PWM duties (0..1) of symbols first_symbol .. first_symbol + n_sym - 1.
    first_symbol : int
        Symbol index of the first row of ``duties``.
    clock : LedClock
        Symbol period T and carrier frequency.
    cum : ndarray, optional
        Precomputed :func:`symbol_cumsum` of ``duties``, (n_sym + 1, N), s.

    Returns
    -------
    ndarray of float64
        (F, N) on-times, s (LED clock).
    """
    T = clock.symbol_period_s
    d = np.asarray(duties, dtype=np.float64)
    if cum is None:
        cum = symbol_cumsum(d, clock)
    n_sym = d.shape[0]
    t = np.asarray(t_led, dtype=np.float64)
    k = np.floor(t / T).astype(np.int64) - first_symbol
    k = np.clip(k, 0, n_sym - 1)  # a time at the very end belongs to the last symbol
    tau = t - (k + first_symbol) * T
    tau = np.clip(tau, 0.0, T)
    return cum[k] + partial_on_time(tau[:, None], d[k], clock.pwm_hz)


def symbol_cumsum(duties: np.ndarray, clock: LedClock) -> np.ndarray:
    """(n_sym + 1, N) cumulative on-time (s) at each symbol start, 0 at the first.

    Parameters
    ----------
    duties : ndarray
        (n_sym, N) PWM duties of consecutive symbols, 0..1.
    clock : LedClock
        Symbol period and carrier frequency.

    Returns
    -------
    ndarray of float64
        (n_sym + 1, N) on-times, s (LED clock).
    """
    d = np.asarray(duties, dtype=np.float64)
    full = partial_on_time(np.full(d.shape, clock.symbol_period_s), d, clock.pwm_hz)
    out = np.zeros((d.shape[0] + 1, d.shape[1]))
    np.cumsum(full, axis=0, out=out[1:])
    return out


def on_time(t0_cam: np.ndarray, exposure_s: float, clock: LedClock,
            duty_of: "callable[[int, int], np.ndarray]") -> np.ndarray:  # type: ignore[valid-type]
    """Integrated on-time (s, camera clock) of every LED in each exposure window.

    Parameters
    ----------
    t0_cam : ndarray
        (F,) exposure start times, s (camera clock); windows are [t0, t0 + exposure_s].
    exposure_s : float
        Exposure time, s.
    clock : LedClock
        The transmitter's clock.
    duty_of : callable
        ``duty_of(k0, k1)``: (k1 - k0, N) PWM duties (0..1) of symbols k0..k1-1
        (negative k: dark).

    Returns
    -------
    ndarray of float64
        (F, N) on-times, s; divide by ``exposure_s`` for the on-time fraction.

    References
    ----------
    SPEC sections 3 and 6.
    """
    t0 = np.asarray(t0_cam, dtype=np.float64).reshape(-1)
    return on_time_window(t0, t0 + exposure_s, clock, duty_of)


def on_time_window(a_cam: np.ndarray, b_cam: np.ndarray, clock: LedClock,
                   duty_of: "callable[[int, int], np.ndarray]") -> np.ndarray:  # type: ignore[valid-type]
    """Integrated on-time (s, camera clock) of every LED in windows [a, b] of their own
    length (e.g. an exposure clipped to the interval in which a transmitter is in view);
    a window with b <= a integrates nothing.

    Parameters
    ----------
    a_cam, b_cam : ndarray
        (F,) window starts and ends, s (camera clock).
    clock : LedClock
        The transmitter's clock.
    duty_of : callable
        ``duty_of(k0, k1)``: (k1 - k0, N) PWM duties (0..1) of symbols k0..k1-1.

    Returns
    -------
    ndarray of float64
        (F, N) on-times, s.
    """
    a = np.asarray(a_cam, dtype=np.float64).reshape(-1)
    b = np.maximum(np.asarray(b_cam, dtype=np.float64).reshape(-1), a)
    T = clock.symbol_period_s
    if a.size == 0:
        return np.zeros((0, duty_of(0, 1).shape[1]))
    ua, ub = clock.led_time(a), clock.led_time(b)
    k0 = int(np.floor(ua.min() / T))
    k1 = int(np.floor(ub.max() / T)) + 1
    d = duty_of(k0, k1)
    cum = symbol_cumsum(d, clock)
    ga = cumulative_on_time(ua, d, k0, clock, cum)
    gb = cumulative_on_time(ub, d, k0, clock, cum)
    out = (gb - ga) / clock.rate
    out[b <= a] = 0.0
    return out


def brute_force_on_time(t0_cam: float, exposure_s: float, clock: LedClock,
                        duty_of: "callable[[int, int], np.ndarray]",  # type: ignore[valid-type]
                        samples_per_pwm_period: int = 400) -> np.ndarray:
    """Reference: sample the carrier waveform densely and sum (tests only).

    Parameters
    ----------
    t0_cam : float
        Exposure start, s (camera clock).
    exposure_s : float
        Exposure time, s.
    clock : LedClock
        The transmitter's clock.
    duty_of : callable
        ``duty_of(k0, k1)``: (k1 - k0, N) PWM duties (0..1) of symbols k0..k1-1.
    samples_per_pwm_period : int
        Midpoint-rule samples per carrier period 1/f_pwm.

    Returns
    -------
    ndarray of float64
        (N,) on-times, s (camera clock).
    """
    n = int(np.ceil(exposure_s * clock.pwm_hz * samples_per_pwm_period))
    dt = exposure_s / n
    t = t0_cam + (np.arange(n) + 0.5) * dt  # midpoint rule
    u = clock.led_time(t)
    T = clock.symbol_period_s
    k = np.floor(u / T).astype(np.int64)
    k0, k1 = int(k.min()), int(k.max()) + 1
    d = duty_of(k0, k1)[k - k0]
    tau = u - k * T
    phase = tau * clock.pwm_hz - np.floor(tau * clock.pwm_hz)
    on = phase[:, None] < d
    return on.sum(axis=0) * dt
