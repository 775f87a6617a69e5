"""Synthetic LED luminance for receiver tests and benchmarks (not the image simulator).

Generates what :mod:`iscd.decode.tracking.luminance` would measure: per frame and LED, the ROI
mean of a small spot whose pixels integrate the PWM waveform over the exposure window,
with per-pixel clipping (saturation), shot and read noise and 8-bit quantization. Time
base as in the simulator (``iscd.sim.exposure``): the LED clock runs at
``t_led = (t_cam - phase_s) * (1 + drift_ppm 1e-6)``; LED symbol k covers
``t_led in [k T, (k+1) T)``, T = 1/f_sym; before symbol 0 and after the last one the LED
is dark. Within a symbol the PWM carrier (period aligned to the symbol start) is on for
the first ``duty / f_pwm`` s of each period (``pwm_hz=None``: ideal, on-time = duty x time).

Everything is vectorized over frames x LEDs (x pixels).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def cumulative_on_time(t_led: np.ndarray, duty_k: np.ndarray, symbol_period_s: float,
                       pwm_hz: float | None) -> np.ndarray:
    """On-time (LED-clock s) from LED time 0 to ``t_led`` for per-symbol duties.

    Times before 0 count nothing; after the last symbol, the total.

    Parameters
    ----------
    t_led : ndarray
        (n,) LED-clock times, s.
    duty_k : ndarray
        (K, N) duty (0..1) of each symbol and LED.
    symbol_period_s : float
        Symbol period T, s.
    pwm_hz : float or None
        PWM carrier frequency, Hz (each period on for its first ``duty / f_pwm`` s); None:
        ideal, on-time = duty x time.

    Returns
    -------
    ndarray of float64
        (n, N) on-time, LED-clock s.

    References
    ----------
    SPEC section 3 (PWM levels), section 6 (exposure integration).
    """
    t = np.asarray(t_led, dtype=np.float64)
    n_sym = duty_k.shape[0]
    T = symbol_period_s
    cum = np.concatenate([np.zeros((1, duty_k.shape[1])), np.cumsum(duty_k, axis=0) * T])
    tc = np.clip(t, 0.0, n_sym * T)
    k = np.minimum((tc // T).astype(np.int64), n_sym - 1)
    u = (tc - k * T)[:, None]  # time into symbol k
    d = duty_k[k]
    if pwm_hz is None:
        part = u * d
    else:
        P = 1.0 / pwm_hz
        whole = np.floor(u / P)
        part = whole * d * P + np.minimum(u - whole * P, d * P)
    return cum[k] + part


def integrated_duty(levels: np.ndarray, n_levels: int, frame_start_s: np.ndarray, exposure_s: float,
                    symbol_rate_hz: float, phase_s: float = 0.0, drift_ppm: float = 0.0,
                    pwm_hz: float | None = 50_000.0) -> np.ndarray:
    """Mean duty x in [0, 1] seen by each exposure window: (frames, N).

    The window is [t, t + exposure_s] on the camera clock; the LED clock is
    ``t_led = (t_cam - phase_s) * (1 + drift_ppm 1e-6)``.

    Parameters
    ----------
    levels : ndarray
        (K, N) 1-based levels sent from LED symbol 0 on.
    n_levels : int
        Number of levels M (duty (s - 1) / (M - 1)).
    frame_start_s : ndarray
        (n,) camera times of exposure start, s.
    exposure_s : float
        Exposure time, s.
    symbol_rate_hz : float
        Symbol rate, Hz.
    phase_s : float
        Camera time of LED symbol 0's start, s.
    drift_ppm : float
        LED clock rate error, ppm (positive = LED fast).
    pwm_hz : float or None
        PWM carrier frequency, Hz (None: ideal).

    Returns
    -------
    ndarray of float64
        (n, N) mean duty, 0 .. 1.

    References
    ----------
    SPEC section 3 (PWM levels), section 6 (exposure integration).
    """
    lv = np.asarray(levels, dtype=np.float64)
    duty_k = (lv - 1.0) / (n_levels - 1)
    rate = 1.0 + drift_ppm * 1e-6
    T = 1.0 / symbol_rate_hz
    t0 = (np.asarray(frame_start_s, dtype=np.float64) - phase_s) * rate
    t1 = t0 + exposure_s * rate
    on = cumulative_on_time(np.concatenate([t0, t1]), duty_k, T, pwm_hz)
    n = t0.size
    return (on[n:] - on[:n]) / (exposure_s * rate)


def gaussian_profile(size: int = 5, sigma_px: float = 1.0) -> np.ndarray:
    """Peak-normalized Gaussian spot over a size x size ROI, flattened (size*size,).

    Parameters
    ----------
    size : int
        ROI width and height, px.
    sigma_px : float
        Spot sigma, px.

    Returns
    -------
    ndarray of float64
        (size * size,) row-major profile, peak 1.
    """
    r = np.arange(size) - (size - 1) / 2
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma_px ** 2))
    return (g / g.max()).reshape(-1)


@dataclass(frozen=True)
class SynthCamera:
    """One camera's view of the LEDs, all in DN (8-bit grey levels).

    peak_dn: peak pixel value of a fully-on LED before clipping (f/4 -> f/8 is / 4).
    offset_dn: background + black level. read_noise_dn: RMS per pixel.
    shot_dn: shot-noise variance per DN of signal (DN/electron; 255/20000 e- ~ 0.0128).
    clip_dn: saturation level. led_gain_spread: RMS relative gain spread between LEDs.
    profile: peak-normalized spot pixels (the ROI), default a 5x5 Gaussian, sigma 1 px.
    """

    peak_dn: float = 120.0
    offset_dn: float = 10.0
    read_noise_dn: float = 1.0
    shot_dn: float = 0.0128
    clip_dn: float = 255.0
    led_gain_spread: float = 0.0
    quantize: bool = True
    profile: np.ndarray = field(default_factory=gaussian_profile)

    def luminance(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """ROI-mean luminance (frames, N) of integrated duty ``x`` (frames, N).

        Per pixel: signal, offset, shot and read noise, rounding (with ``quantize``) and clipping
        at ``clip_dn``; each LED's gain drawn once per call (``led_gain_spread``).

        Parameters
        ----------
        x : ndarray
            (n, N) integrated duty, 0 .. 1 (:func:`integrated_duty`).
        rng : numpy.random.Generator
            Noise source.

        Returns
        -------
        ndarray of float64
            (n, N) ROI-mean luminance, DN.
        """
        n, N = x.shape
        gains = self.peak_dn * (1.0 + self.led_gain_spread * rng.standard_normal(N))
        prof = np.asarray(self.profile, dtype=np.float64)
        out = np.empty((n, N))
        step = max(1, 2_000_000 // max(1, N * prof.size))
        for a in range(0, n, step):  # chunks bound memory; the inner work is vectorized
            xs = x[a:a + step]
            sig = xs[:, :, None] * gains[None, :, None] * prof[None, None, :]
            var = self.read_noise_dn ** 2 + self.shot_dn * sig
            pix = sig + self.offset_dn + np.sqrt(var) * rng.standard_normal(sig.shape)
            if self.quantize:
                pix = np.rint(pix)
            np.clip(pix, 0.0, self.clip_dn, out=pix)
            out[a:a + step] = pix.mean(axis=2)
        return out


@dataclass
class SynthRecording:
    """Synthetic luminance of a stereo pair and its truth.

    t_s: (n,) frame start times, s. L: (C, n, N) luminance per camera. x: (n, N) true mean
    duty per frame. levels: (K, N) levels sent from LED symbol 0. packet_starts_s: camera
    time of each packet's first header symbol, s. payloads: the packets' payloads.
    packet_symbol0: LED symbol index of each packet's first header symbol.
    """

    t_s: np.ndarray
    L: np.ndarray
    x: np.ndarray
    levels: np.ndarray
    packet_starts_s: np.ndarray
    packet_symbol0: np.ndarray
    payloads: list[bytes]
    fps: float
    exposure_s: float


def synth_recording(air: object, cams: list[SynthCamera], n_packets: int = 2, *,
                    fps: float = 1000.0, exposure_s: float = 1e-3, symbol_rate_hz: float = 500.0,
                    pwm_hz: float | None = 50_000.0, phase_s: float = 0.0123,
                    drift_ppm: float = 100.0, lead_symbols: int = 7, tail_symbols: int = 20,
                    start_s: float = 0.0, seed: int = 0,
                    payloads: list[bytes] | None = None) -> SynthRecording:
    """Back-to-back packets of random payloads seen by ``cams``.

    ``lead_symbols`` random data symbols precede the first header (so the recording starts
    mid-transmission), ``tail_symbols`` random ones follow the last packet. The recording
    covers camera time ``start_s`` to the end of the tail; ``start_s`` past the first
    header start gives a recording that begins mid-packet.

    Parameters
    ----------
    air : AirInterface or AirInterfaceV2
        The air interface (M, N, packet geometry).
    cams : list of SynthCamera
        The cameras (C of them).
    n_packets : int
        Number of packets (when ``payloads`` is not given).
    fps : float
        Frame rate, frames/s.
    exposure_s : float
        Exposure time, s.
    symbol_rate_hz : float
        Symbol rate, Hz.
    pwm_hz : float or None
        PWM carrier frequency, Hz (None: ideal).
    phase_s : float
        Camera time of LED symbol 0's start, s.
    drift_ppm : float
        LED clock rate error, ppm (positive = LED fast).
    lead_symbols : int
        Random symbols before the first header, symbols.
    tail_symbols : int
        Random symbols after the last packet, symbols.
    start_s : float
        Camera time of the first frame's exposure start, s.
    seed : int
        Seed of the random payloads, symbols and noise.
    payloads : list of bytes, optional
        The packets' payloads (default: ``n_packets`` random ones).

    Returns
    -------
    SynthRecording
        Luminance (C, n, N), DN, frame times, s, and the truth.
    """
    from iscd.core.airinterface import AirInterface, random_payload
    from iscd.core.airinterface_v2 import AirInterfaceV2

    assert isinstance(air, (AirInterface, AirInterfaceV2))
    rng = np.random.default_rng(seed)
    if payloads is None:
        payloads = [random_payload(air, rng) for _ in range(n_packets)]
    M, N = air.levels, air.n_leds
    lead = rng.integers(1, M + 1, size=(lead_symbols, N)).astype(np.uint8)
    tail = rng.integers(1, M + 1, size=(tail_symbols, N)).astype(np.uint8)
    levels = np.concatenate([lead, air.packets(payloads), tail])
    rate = 1.0 + drift_ppm * 1e-6
    T = 1.0 / symbol_rate_hz
    sym0 = lead_symbols + air.period_symbols * np.arange(len(payloads))
    starts = sym0 * T / rate + phase_s
    t_end = levels.shape[0] * T / rate + phase_s
    n_frames = int(np.floor((t_end - start_s - exposure_s) * fps + 1e-9)) + 1
    t = start_s + np.arange(n_frames) / fps
    x = integrated_duty(levels, M, t, exposure_s, symbol_rate_hz, phase_s, drift_ppm, pwm_hz)
    L = np.stack([c.luminance(x, rng) for c in cams])
    return SynthRecording(t_s=t, L=L, x=x, levels=levels, packet_starts_s=starts,
                          packet_symbol0=sym0, payloads=list(payloads), fps=fps,
                          exposure_s=exposure_s)


def render_spots(x: np.ndarray, centres: np.ndarray, shape: tuple[int, int], peak_dn: float,
                 sigma_px: float = 0.8, background_dn: float | np.ndarray = 20.0,
                 read_noise_dn: float = 1.0, shot_dn: float = 0.0128, clip_dn: float = 255.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """8-bit frames (F, H, W) of Gaussian LED spots: LED i at ``centres[i]`` (x, y px)
    with peak ``peak_dn * x[f, i]`` over a background, noise, rounding and clipping.

    Parameters
    ----------
    x : ndarray
        (F, N) relative brightness of each LED in each frame (e.g. integrated duty, 0 .. 1).
    centres : ndarray
        (N, 2) LED centres (x, y), px.
    shape : (int, int)
        Image shape (H, W), px.
    peak_dn : float
        Peak pixel value of a spot at x = 1 before clipping, DN.
    sigma_px : float
        Spot sigma, px.
    background_dn : float or ndarray
        Background, DN: one value or an (H, W) image.
    read_noise_dn : float
        Read noise RMS per pixel, DN.
    shot_dn : float
        Shot-noise variance per DN of signal, DN.
    clip_dn : float
        Saturation level, DN.
    rng : numpy.random.Generator, optional
        Noise source (default seeded with 0).

    Returns
    -------
    ndarray of uint8
        (F, H, W) frames, DN.
    """
    rng = rng or np.random.default_rng(0)
    H, W = shape
    c = np.asarray(centres, dtype=np.float64)
    yy, xx = np.mgrid[0:H, 0:W]
    prof = np.exp(-((xx[None] - c[:, 0, None, None]) ** 2 + (yy[None] - c[:, 1, None, None]) ** 2)
                  / (2 * sigma_px ** 2))  # (N, H, W)
    sig = np.tensordot(np.asarray(x, dtype=np.float64) * peak_dn, prof, axes=(1, 0))  # (F, H, W)
    img = sig + background_dn
    img = img + np.sqrt(read_noise_dn ** 2 + shot_dn * np.maximum(sig, 0)) * rng.standard_normal(img.shape)
    return np.clip(np.rint(img), 0, clip_dn).astype(np.uint8)
