"""A second night model, written apart from the generator's (night.py): a night camera simulated in linear light.

A validation set rendered by the same code as the training scenes measures how well a model learned that code's
fingerprint. This model shares no code path with it; it follows the physics of a small video camera at night
instead. The day frame is linearised (inverse sRGB); the scene is lit by a fraction of daylight (an ambient
level and pools under street lamps, irradiance falling off as from a lamp on a pole) in the lamp's colour
(sodium, warm or cool LED, mercury vapour) and dimmed towards the corners (lens vignetting); the sensor collects
electrons in the exposure time (Poisson shot noise, capped at the full well), adds read noise (Gaussian) on a
black-level pedestal and digitises at 10 or 12 bits; auto-exposure sets the ISO gain on the first frame up to
the camera's limit (at night it runs out, so frames come out dark); then the camera subtracts the black level
(a little high, crushing the darkest noise), white-balances part of the cast away, desaturates, applies its
response curve, denoises (motion-adaptive temporal filtering and a bilateral or non-local-means filter),
sharpens (unsharp mask) and compresses (JPEG at night quality). Every parameter is drawn once per sequence
(`NightCamera.draw`) so the lights stay fixed in the image and the look holds for the whole sequence, and is
recorded (`NightCamera.record`). The ranges were set so that rendered frames of real video land in the
statistics of real night drone video (`night_statistics`; docs/datasets.md, "A second night model").

H.264 would be the compression of a real camera, but this OpenCV's FFmpeg has no H.264 encoder and ignores the
bitrate of the one it has (MPEG-4 part 2), so frames are compressed as JPEG at qualities 20-60.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

MODEL = "camera"  # the name this night model goes by in commands and benchmark.json

# Linear-light (B, G, R) gains of each lamp's light as a colour camera sees it, the brightest channel 1.
# High-pressure sodium is nearly monochromatic at 589 nm (orange: little blue); warm LEDs are phosphor-white at
# ~3000 K, cool LEDs at ~5000 K; mercury vapour lines are blue-green with little red.
LAMPS: dict[str, tuple[float, float, float]] = {
    "sodium": (0.08, 0.40, 1.0),
    "led_warm": (0.45, 0.74, 1.0),
    "led_cool": (0.92, 1.0, 0.90),
    "mercury": (0.85, 1.0, 0.48),
}
LAMP_ODDS = {"sodium": 0.4, "led_warm": 0.2, "led_cool": 0.2, "mercury": 0.2}
MOONLIGHT = (1.0, 0.93, 0.80)  # the sky's ambient light, bluish (B, G, R)
DAY_EXPOSURE_S = 1 / 500  # the day frame is taken as a correct exposure at this time...
DAY_PHOTONS = 20_000.0  # ... in which a white surface sends this many photons to a pixel (a ~2 um pixel)
HEAD_BRIGHTNESS = 30.0  # a lamp in view over the ground at its pool's peak
LUMA = np.array([0.114, 0.587, 0.299], np.float32)  # B, G, R weights of luma


@dataclass(frozen=True)
class Pool:
    """A street lamp's pool of light: centre (fraction of width, height), radius (fraction of the diagonal:
    the lamp's height above what is lit), peak irradiance as a multiple of the ambient level, and the lamp
    itself where it is in view: a glow of `head` px (sigma) above the pool's centre (0: out of view)."""

    x: float
    y: float
    radius: float
    peak: float
    head: float


@dataclass(frozen=True)
class NightCamera:
    """One camera at one place at night; `draw` picks every value, `render` films a sequence with it."""

    lamp: str
    lamp_gains: tuple[float, float, float]  # B, G, R linear gains of the lamp's light (after a per-lamp jitter)
    moonlight_share: float  # share of the ambient light that is the sky's rather than the lamps'
    illuminance: float  # ambient night illuminance as a fraction of the day frame's
    pools: tuple[Pool, ...]
    vignetting: float  # irradiance lost at the frame's corner (cos^4-like falloff)
    exposure_s: float  # exposure time
    full_well: float  # electrons a pixel holds
    quantum_efficiency: float  # electrons per photon
    read_noise: float  # electrons, Gaussian
    black_level: float  # pedestal, fraction of full scale
    black_crush: float  # how far above the pedestal the camera sets black, in read-noise sigmas (a noise floor)
    bits: int  # ADC depth
    max_gain: float  # the highest ISO gain (over the gain at which the full well fills full scale): 80-400 e- fill it
    ae_target: float  # mean linear level the auto-exposure aims at...
    highlight_target: float  # ... unless the brightest 0.5 % would go above this linear level
    white_balance: float  # 0: the lamp's cast kept, 1: fully corrected
    saturation: float  # colour kept by the camera's night mode (1: all)
    gamma: float  # response curve exponent (output = linear ** (1 / gamma))
    toe: float  # shadow contrast of the response curve (0: a plain power law)
    temporal: float  # weight of the previous output in the temporal denoiser where nothing moved (0: off)
    spatial: str  # spatial denoiser: "bilateral" or "nlmeans"
    denoise_strength: float  # the luma filter's strength over the noise the camera estimates
    chroma_blur: float  # sigma (px) of the chroma noise reduction
    sharpen: float  # unsharp-mask amount
    sharpen_sigma: float  # unsharp-mask radius, px
    jpeg_quality: int

    @classmethod
    def draw(cls, rng: np.random.Generator) -> NightCamera:
        """A camera, its settings and the lights of its scene, drawn from ranges that cover real night video."""
        lamp = str(rng.choice(list(LAMP_ODDS), p=list(LAMP_ODDS.values())))
        gains = np.array(LAMPS[lamp]) * np.exp(rng.normal(0, 0.08, 3))
        gains /= gains.max()
        pools = tuple(
            Pool(x=float(rng.uniform(0.05, 0.95)), y=float(rng.uniform(0.05, 0.95)),
                 radius=float(rng.uniform(0.04, 0.2)), peak=float(np.exp(rng.uniform(np.log(15), np.log(120)))),
                 head=float(rng.choice([0.0, rng.uniform(1.5, 4.0)])))
            for _ in range(int(rng.choice([1, 1, 2, 2, 3, 3, 4]))))
        spatial = str(rng.choice(["bilateral", "nlmeans"]))
        full_well = float(rng.uniform(5000, 15000))
        brightest = float(np.exp(rng.uniform(np.log(80), np.log(400))))  # electrons at full scale, top ISO
        return cls(
            lamp=lamp,
            lamp_gains=tuple(round(float(g), 4) for g in gains),
            moonlight_share=float(rng.uniform(0.0, 0.4)),
            illuminance=float(np.exp(rng.uniform(np.log(1.2e-5), np.log(4e-5)))),
            pools=pools,
            vignetting=float(rng.uniform(0.1, 0.6)),
            exposure_s=float(rng.choice([1 / 25, 1 / 30, 1 / 50])),
            full_well=full_well,
            max_gain=full_well / brightest,
            quantum_efficiency=float(rng.uniform(0.4, 0.8)),
            read_noise=float(rng.uniform(1.5, 6.0)),
            black_level=float(rng.uniform(0.02, 0.07)),
            black_crush=float(rng.uniform(0.3, 1.2)),
            bits=int(rng.choice([10, 12])),
            ae_target=float(rng.uniform(0.05, 0.12)),
            highlight_target=float(rng.uniform(0.5, 0.9)),
            white_balance=float(rng.uniform(0.0, 0.3)),
            saturation=float(rng.uniform(0.5, 1.0)),
            gamma=float(rng.uniform(1.9, 2.4)),
            toe=float(rng.uniform(0.2, 0.7)),
            temporal=float(rng.uniform(0.0, 0.7)),
            spatial=spatial,
            denoise_strength=float(rng.uniform(0.8, 1.6)),
            chroma_blur=float(rng.uniform(1.5, 4.0)),
            sharpen=float(rng.uniform(0.1, 0.6)),
            sharpen_sigma=float(rng.uniform(0.8, 2.0)),
            jpeg_quality=int(rng.integers(20, 61)),
        )

    def record(self) -> dict:
        """Every setting, as JSON-ready values (what benchmark.json keeps for each sequence)."""
        return {"model": MODEL, **asdict(self)}

    def irradiance(self, width: int, height: int) -> np.ndarray:
        """(H, W, 3) light falling on the scene, B G R, as a fraction of the day frame's: ambient, pools, vignette."""
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
        diagonal = float(np.hypot(width, height))
        pooled = np.zeros((height, width), np.float32)
        for pool in self.pools:
            r2 = ((xs - pool.x * width) ** 2 + (ys - pool.y * height) ** 2) / (pool.radius * diagonal) ** 2
            pooled += pool.peak / (1 + r2) ** 1.5  # irradiance under a point source at height `radius`
        vignette = 1 - self.vignetting * ((xs - width / 2) ** 2 + (ys - height / 2) ** 2) / (diagonal / 2) ** 2
        lamp = np.array(self.lamp_gains, np.float32)
        ambient = self.moonlight_share * np.array(MOONLIGHT, np.float32) + (1 - self.moonlight_share) * lamp
        light = vignette[..., None] * (ambient + pooled[..., None] * lamp)  # the pools are the lamps' alone
        return (self.illuminance * light).astype(np.float32)

    def glow(self, width: int, height: int) -> np.ndarray:
        """(H, W, 3) light sent by the lamps in view, in the units of a white surface's under `irradiance`: a
        lamp is HEAD_BRIGHTNESS times brighter than the ground at its pool's peak, so it saturates."""
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
        diagonal = float(np.hypot(width, height))
        emitted = np.zeros((height, width), np.float32)
        for pool in (p for p in self.pools if p.head > 0):
            x = pool.x * width
            y = max(pool.y * height - 0.5 * pool.radius * diagonal, 0.0)  # on its pole, above the pool
            emitted += pool.peak * HEAD_BRIGHTNESS * np.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * pool.head**2))
        return (self.illuminance * emitted[..., None] * np.array(self.lamp_gains, np.float32)).astype(np.float32)

    def expected_electrons(self, day: np.ndarray, light: np.ndarray, glow: np.ndarray) -> np.ndarray:
        """Mean electrons per pixel and channel: the day frame's linear radiance under the night's light, and
        the lamps in view."""
        scale = DAY_PHOTONS * self.quantum_efficiency * self.exposure_s / DAY_EXPOSURE_S
        return (srgb_to_linear(day) * light + glow) * np.float32(scale)

    def gain_for(self, electrons: np.ndarray) -> float:
        """ISO gain the auto-exposure picks: the frame's mean at `ae_target` unless that would clip more than
        the brightest 0.5 % (lamp pools keep their detail), up to the camera's limit."""
        luma = (electrons @ LUMA) / self.full_well
        mean, bright = float(luma.mean()), float(np.percentile(luma, 99.5))
        wanted = min(self.ae_target / max(mean, 1e-9), self.highlight_target / max(bright, 1e-9))
        return float(np.clip(wanted, 1.0, self.max_gain))

    def sensor(self, electrons: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
        """Shot noise, full well, read noise, pedestal and ADC: the raw frame, linear, black at 0 (noise below
        it kept), white at 1."""
        collected = np.minimum(rng.poisson(electrons).astype(np.float32), self.full_well)
        signal = collected + np.float32(self.read_noise) * rng.standard_normal(collected.shape, dtype=np.float32)
        raw = signal * np.float32(gain / self.full_well) + np.float32(self.black_level)
        levels = 2**self.bits - 1
        raw = np.round(np.clip(raw, 0, 1) * levels) / levels
        black = self.black_level + self.black_crush * self.read_noise * gain / self.full_well
        return np.minimum((raw - black) / (1 - black), 1)  # below black stays signed until the response curve

    def develop(self, raw: np.ndarray) -> np.ndarray:
        """White balance, chroma noise reduction (a blur of the colour, in linear light where the noise still
        averages out), saturation and the response curve: the 8-bit picture before denoising (float)."""
        lamp = np.array(self.lamp_gains, np.float32)
        balance = (float(lamp @ LUMA) / lamp) ** np.float32(self.white_balance)
        image = raw * balance
        luma = (image @ LUMA)[..., None]
        chroma = cv2.GaussianBlur(image - luma, (0, 0), self.chroma_blur)
        image = np.clip(luma + self.saturation * chroma, 0, 1)
        curve = image ** np.float32(1 / self.gamma)
        curve = curve * (1 - self.toe) + self.toe * curve**2  # a toe: shadows pressed down, white stays white
        return curve * 255

    def noise_level(self, picture: np.ndarray) -> float:
        """The camera's estimate of its noise (grey levels, luma) on a developed frame, as an ISP's noise profile
        gives it for the gain in use: the median absolute high-pass in the darker half of what is above black,
        as a Gaussian's sigma."""
        luma = picture @ LUMA
        detail = np.abs(luma - cv2.GaussianBlur(luma, (0, 0), 1.0))
        lit = luma > 2
        if not lit.any():
            return 0.0
        darker = lit & (luma <= np.median(luma[lit]))
        return float(np.median(detail[darker]) / 0.6745 * 1.25)  # the blur removes part of the noise; sigma

    def denoise(self, picture: np.ndarray, previous: np.ndarray | None, noise: float) -> np.ndarray:
        """Motion-adaptive temporal averaging with the previous output, then the spatial filter on luma, both
        set by the `noise` estimate (the colour was smoothed in `develop`)."""
        if previous is not None and self.temporal > 0:
            change = cv2.GaussianBlur(np.abs(picture - previous).mean(axis=2), (0, 0), 1.5)
            keep = self.temporal * np.exp(-change / (2 + 2 * noise))[..., None]  # moving parts are not averaged
            picture = keep * previous + (1 - keep) * picture
        image = np.clip(np.round(picture), 0, 255).astype(np.uint8)
        luma, red, blue = cv2.split(cv2.cvtColor(image, cv2.COLOR_BGR2YCrCb))
        strength = self.denoise_strength * max(noise, 1.0)
        if self.spatial == "nlmeans":
            luma = cv2.fastNlMeansDenoising(luma, None, strength, 3, 7)
        else:
            luma = cv2.bilateralFilter(luma, 7, 2.5 * strength, 3)
        return cv2.cvtColor(cv2.merge([luma, red, blue]), cv2.COLOR_YCrCb2BGR)

    def finish(self, image: np.ndarray) -> np.ndarray:
        """Unsharp mask and JPEG compression: the frame as the camera delivers it."""
        soft = cv2.GaussianBlur(image, (0, 0), self.sharpen_sigma)
        sharp = cv2.addWeighted(image, 1 + self.sharpen, soft, -self.sharpen, 0)
        ok, data = cv2.imencode(".jpg", sharp, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("OpenCV could not JPEG-encode a frame")
        return cv2.imdecode(data, cv2.IMREAD_COLOR)

    def render(self, day: list[np.ndarray], seed: list[int]) -> tuple[list[np.ndarray], dict]:
        """The night of a sequence of day frames (BGR uint8, one size) and what the camera locked on its first
        frame (ISO gain, noise estimate); frame i's noise is drawn from `seed + [i]`, the temporal denoiser
        carries from frame to frame."""
        height, width = day[0].shape[:2]
        light, glow = self.irradiance(width, height), self.glow(width, height)
        gain = noise = previous = None
        night = []
        for i, frame in enumerate(day):
            if frame.shape != day[0].shape:
                raise ValueError(f"frame {i + 1} is {frame.shape[1]}x{frame.shape[0]}, not {width}x{height}")
            electrons = self.expected_electrons(frame, light, glow)
            gain = self.gain_for(electrons) if gain is None else gain
            picture = self.develop(self.sensor(electrons, gain, np.random.default_rng([*seed, i])))
            noise = self.noise_level(picture) if noise is None else noise
            denoised = self.denoise(picture, previous, noise)
            previous = denoised.astype(np.float32)
            night.append(self.finish(denoised))
        return night, {"gain": round(gain, 3), "noise_estimate": round(noise, 3)}


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """8-bit sRGB to linear light in [0, 1] (IEC 61966-2-1), float32."""
    lut = np.arange(256, dtype=np.float32) / 255
    lut = np.where(lut <= 0.04045, lut / 12.92, ((lut + 0.055) / 1.055) ** 2.4).astype(np.float32)
    return lut[image]


def render_night(day: list[np.ndarray], seed: list[int]) -> tuple[list[np.ndarray], dict]:
    """The night of `day` filmed by a camera drawn from `seed`, and the record of that camera: every drawn
    setting and what it locked on the first frame."""
    camera = NightCamera.draw(np.random.default_rng([*seed, 0]))
    night, locked = camera.render(day, [*seed, 1])
    return night, {**camera.record(), **locked}


def night_statistics(frame: np.ndarray) -> dict[str, float]:
    """The statistics of ../shared/notes/real-night-footage.md for one BGR uint8 frame: mean luma, B/G/R means,
    share of pixels below 20 and above 245, and the noise in dark areas (std of luma less its sigma-2 blur where
    the sigma-4 blur is below 40)."""
    luma = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY).astype(np.float32)
    dark = cv2.GaussianBlur(luma, (0, 0), 4) < 40
    detail = luma - cv2.GaussianBlur(luma, (0, 0), 2)
    blue, green, red = (float(frame[..., k].mean()) for k in range(3))
    return {
        "mean": float(luma.mean()),
        "blue": blue,
        "green": green,
        "red": red,
        "below_20": float((luma < 20).mean()),
        "above_245": float((luma > 245).mean()),
        "noise": float(detail[dark].std()) if dark.any() else float("nan"),
    }
