"""Optional temporal filter: a constant-velocity Kalman filter on range and closing speed.

State ``[Z (m), V (m/s)]`` with ``dZ/dt = V`` (V < 0 when approaching; ``closing_speed``
is ``-V``), driven by white acceleration noise of spectral density ``accel_psd``
((m/s^2)^2 per Hz). Each per-frame range ``z`` with its standard deviation ``sigma``
(:mod:`iscd.decode.ranging.range`) is one measurement. Measurements whose innovation is beyond
``gate`` standard deviations are rejected (counted, not applied) so one bad match cannot
throw the track; after ``max_rejects`` rejections in a row the filter restarts from the
next measurement. The filtered figures are always reported separately from the per-frame
ones (SPEC: a temporal filter is an option, never a replacement).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class TrackState:
    """The filter's estimate after a step."""

    t_s: float
    z_m: float
    speed_mps: float
    """dZ/dt, m/s (negative when closing in)."""
    sigma_z_m: float
    sigma_v_mps: float
    accepted: bool
    """whether this step's measurement was used."""

    @property
    def closing_speed_mps(self) -> float:
        return -self.speed_mps


class RangeKalman:
    """Constant-velocity Kalman filter for one transmitter's range (see the module doc).

    ``accel_psd``: process noise, (m/s^2)^2/Hz (1.0 ~ gentle braking/acceleration changes).
    ``init_speed_sigma``: prior standard deviation of V at the first measurement, m/s.
    """

    def __init__(self, accel_psd: float = 1.0, gate: float = 5.0, init_speed_sigma: float = 20.0,
                 max_rejects: int = 10) -> None:
        if not (accel_psd > 0 and gate > 0 and init_speed_sigma > 0 and max_rejects >= 1):
            raise ValueError("RangeKalman: accel_psd, gate, init_speed_sigma must be > 0, max_rejects >= 1")
        self.q = float(accel_psd)
        self.gate = float(gate)
        self.v0 = float(init_speed_sigma)
        self.max_rejects = int(max_rejects)
        self.reset()

    def reset(self) -> None:
        """Forget the track; the next measurement starts a new one."""
        self.t: float | None = None
        self.z = self.v = 0.0
        self.pzz = self.pzv = self.pvv = 0.0
        self.rejects = 0
        self.rejected_total = 0

    @property
    def started(self) -> bool:
        return self.t is not None

    def predict(self, t_s: float) -> tuple[float, float, float]:
        """Range, its sigma and speed predicted at ``t_s`` (no state change).

        Parameters
        ----------
        t_s : float
            Time, s.

        Returns
        -------
        z_m : float
            Predicted range, m.
        sigma_z_m : float
            Its standard deviation, m.
        speed_mps : float
            dZ/dt, m/s.
        """
        if self.t is None:
            return math.nan, math.nan, math.nan
        dt = t_s - self.t
        z = self.z + self.v * dt
        pzz = self.pzz + 2 * dt * self.pzv + dt * dt * self.pvv + self.q * dt ** 3 / 3.0
        return z, math.sqrt(max(pzz, 0.0)), self.v

    def update(self, t_s: float, z_m: float, sigma_m: float) -> TrackState:
        """Advance to ``t_s`` and use the measurement ``z_m`` +- ``sigma_m``.

        NaN/inf/non-positive ``z_m`` or ``sigma_m`` only advance the prediction.

        Parameters
        ----------
        t_s : float
            Time of the measurement, s (increasing).
        z_m : float
            Measured range, m.
        sigma_m : float
            Its standard deviation, m.

        Returns
        -------
        TrackState
            The estimate after the step (``accepted``: whether the measurement was used).
        """
        good = math.isfinite(z_m) and math.isfinite(sigma_m) and sigma_m > 0 and z_m > 0
        if self.t is None:
            if not good:
                return TrackState(t_s, math.nan, math.nan, math.nan, math.nan, False)
            self.t, self.z, self.v = t_s, z_m, 0.0
            self.pzz, self.pzv, self.pvv = sigma_m ** 2, 0.0, self.v0 ** 2
            return self._state(True)
        dt = t_s - self.t
        if dt < 0:
            raise ValueError(f"RangeKalman.update: time went backwards ({self.t} -> {t_s})")
        # predict: x = F x, P = F P F^T + Q (white-acceleration model)
        q = self.q
        self.z += self.v * dt
        pzz = self.pzz + 2 * dt * self.pzv + dt * dt * self.pvv + q * dt ** 3 / 3.0
        pzv = self.pzv + dt * self.pvv + q * dt ** 2 / 2.0
        pvv = self.pvv + q * dt
        self.pzz, self.pzv, self.pvv, self.t = pzz, pzv, pvv, t_s
        if not good:
            return self._state(False)
        s = pzz + sigma_m ** 2
        innov = z_m - self.z
        if innov * innov > self.gate ** 2 * s:
            self.rejects += 1
            self.rejected_total += 1
            if self.rejects >= self.max_rejects:      # the track is lost: restart from here
                self.reset()
                return self.update(t_s, z_m, sigma_m)
            return self._state(False)
        self.rejects = 0
        kz, kv = pzz / s, pzv / s
        self.z += kz * innov
        self.v += kv * innov
        self.pzz, self.pzv, self.pvv = (1 - kz) * pzz, (1 - kz) * pzv, pvv - kv * pzv
        return self._state(True)

    def _state(self, accepted: bool) -> TrackState:
        assert self.t is not None
        return TrackState(self.t, self.z, self.v, math.sqrt(max(self.pzz, 0.0)),
                          math.sqrt(max(self.pvv, 0.0)), accepted)
