"""A third night renderer: day video re-shot by a small low-cost CMOS camera under street lighting.

Written independently of the project's other night renderers so that a tracker trained on their look can be tested
on a look it has never seen. The camera is a cheap drone/surveillance module: a small-pixel Bayer sensor read out
at a capped gain by an auto-exposure loop, then a budget ISP that white-balances only partly, denoises hard, smears
chroma and compresses to low-quality JPEG. Every look parameter is drawn once per sequence; only noise is per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

MODEL = "sensor"  # the name this night model goes by in commands

# Lamp colours as linear-RGB gains relative to daylight (R, G, B), normalised to unit luminance below. Sodium lamps
# emit almost no blue, mercury almost no red; LEDs and halides are broadband with a warm or cool tilt.
_LAMPS: dict[str, tuple[float, float, float]] = {
    "low_pressure_sodium": (1.0, 0.30, 0.01),
    "high_pressure_sodium": (1.0, 0.42, 0.06),
    "warm_led": (1.0, 0.62, 0.30),
    "cool_led": (0.82, 0.90, 1.0),
    "metal_halide": (1.0, 0.88, 0.62),
    "mercury": (0.50, 0.88, 1.0),
    "fluorescent": (0.78, 1.0, 0.72),
}
# Sodium is still the commonest street lamp, LEDs are catching up; how often each lamp is the main one.
_LAMP_WEIGHTS = {
    "low_pressure_sodium": 0.07,
    "high_pressure_sodium": 0.28,
    "warm_led": 0.18,
    "cool_led": 0.18,
    "metal_halide": 0.12,
    "mercury": 0.07,
    "fluorescent": 0.10,
}
_SKY = {"moonlight": (0.78, 0.88, 1.0), "urban_skyglow": (1.0, 0.72, 0.45), "overcast_city": (1.0, 0.85, 0.70)}
_BAYER = {
    "RGGB": cv2.COLOR_BayerRGGB2BGR,
    "BGGR": cv2.COLOR_BayerBGGR2BGR,
    "GRBG": cv2.COLOR_BayerGRBG2BGR,
    "GBRG": cv2.COLOR_BayerGBRG2BGR,
}
_BAYER_EA = {
    "RGGB": cv2.COLOR_BayerRGGB2BGR_EA,
    "BGGR": cv2.COLOR_BayerBGGR2BGR_EA,
    "GRBG": cv2.COLOR_BayerGRBG2BGR_EA,
    "GBRG": cv2.COLOR_BayerGBRG2BGR_EA,
}
_LUMA_BGR = np.array([0.0722, 0.7152, 0.2126], np.float32)  # BT.709 luminance weights in BGR order
_LUT_SIZE = 65536


def _r(x: float) -> float:
    return round(float(x), 4)


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _lamp_bgr(name: str) -> np.ndarray:
    """A lamp's colour in BGR order, normalised to unit luminance so the lamp choice changes hue, not brightness."""
    r, g, b = _LAMPS.get(name, _SKY.get(name, (1.0, 1.0, 1.0)))
    bgr = np.array([b, g, r], np.float32)
    return bgr / float(bgr @ _LUMA_BGR)


@dataclass
class _Look:
    """Everything drawn for one sequence: scalars for the record plus the per-pixel maps built from them."""

    record: dict
    illum: np.ndarray  # H x W x 3 linear illumination (fraction of daylight), BGR
    emit: np.ndarray  # H x W x 3 additive lamp-head radiance, BGR
    dark_e: np.ndarray  # H x W dark electrons per frame (DSNU with hot pixels)
    prnu: np.ndarray  # H x W pixel gain non-uniformity
    offset_e: np.ndarray  # H x W row + column fixed-pattern offsets in electrons
    cfa: np.ndarray  # H x W colour-filter index (0=B, 1=G, 2=R) of each photosite
    meter_w: np.ndarray  # metering weights on the 4x-subsampled raw
    tone_lut: np.ndarray  # linear [0, 1] -> 0..255 display value (tone curve then transfer function)
    motion_kernel: np.ndarray | None


def _draw_record(rng: np.random.Generator) -> dict:
    """Draw the sequence's scalar parameters; independent of frame size and sequence length."""
    rec: dict = {"model": MODEL}
    # Scene lighting: a few lamps (some visible in frame), dim sky ambient, overall level a small fraction of day.
    main = str(rng.choice(list(_LAMP_WEIGHTS), p=np.array(list(_LAMP_WEIGHTS.values())) / sum(_LAMP_WEIGHTS.values())))
    second = str(rng.choice([k for k in _LAMPS if k != main])) if rng.random() < 0.35 else None
    n_lights = int(rng.integers(2, 7))
    lights = []
    for i in range(n_lights):
        lamp = second if second is not None and i > 0 and rng.random() < 0.4 else main
        lights.append(
            {
                "lamp": lamp,
                "x": _r(rng.uniform(-0.15, 1.15)),
                "y": _r(rng.uniform(-0.1, 0.95)),
                "spread": _r(_loguniform(rng, 0.06, 0.30)),  # lamp height as a share of the frame diagonal
                "squash": _r(rng.uniform(0.45, 1.0)),  # pools on the ground look flattened by perspective
                "intensity": _r(_loguniform(rng, 0.5, 2.5)),
                "visible": bool(rng.random() < 0.55),
                "head_size": _r(rng.uniform(0.002, 0.007)),  # lamp-head radius, share of the diagonal
            }
        )
    rec["lamps"] = sorted({lt["lamp"] for lt in lights})
    rec["lights"] = lights
    rec["illumination_fraction"] = _r(_loguniform(rng, 1 / 250, 1 / 30))
    rec["ambient"] = _r(_loguniform(rng, 0.02, 0.15))
    rec["ambient_light"] = str(rng.choice([*_SKY, main]))
    rec["vignetting"] = _r(rng.uniform(0.15, 0.45))
    # Optics and shake: a soft cheap lens and a little blur from the long night exposure.
    rec["optics_blur_px"] = _r(rng.uniform(0.4, 1.1))
    rec["motion_blur_px"] = _r(rng.uniform(0.0, 3.0) if rng.random() < 0.6 else 0.0)
    rec["motion_angle_deg"] = _r(rng.uniform(0.0, 180.0))
    # Sensor: small pixels, low full well, modest read noise; raw response green-heavy as real silicon is.
    rec["bayer"] = str(rng.choice(list(_BAYER)))
    bits = int(rng.choice([10, 12]))
    rec["adc_bits"] = bits
    rec["black_level_dn"] = int(rng.choice([16, 32, 64]) * (4 if bits == 12 else 1))
    rec["full_well_e"] = _r(_loguniform(rng, 3500, 10000))
    rec["sensitivity"] = _r(rng.uniform(0.6, 1.2))  # electrons per unit day-white, as a share of full well
    rec["sensor_bgr"] = [_r(rng.uniform(0.55, 0.8)), 1.0, _r(rng.uniform(0.45, 0.7))]
    rec["read_noise_e"] = _r(rng.uniform(1.2, 3.5))
    rec["adc_noise_dn"] = _r(rng.uniform(0.3, 1.0))
    rec["dark_current_e"] = _r(_loguniform(rng, 0.1, 1.0))
    rec["dsnu"] = _r(rng.uniform(0.2, 0.6))
    rec["hot_pixels_per_million"] = _r(_loguniform(rng, 20.0, 200.0))
    rec["prnu"] = _r(rng.uniform(0.005, 0.02))
    rec["row_fpn_e"] = _r(rng.uniform(0.1, 0.6))
    rec["col_fpn_e"] = _r(rng.uniform(0.05, 0.3))
    rec["row_noise_e"] = _r(rng.uniform(0.05, 0.35))
    # Auto exposure: gain only (shutter already at its longest), converging from a start value, capped.
    max_gain = _loguniform(rng, 12.0, 48.0)
    rec["ae"] = {
        "target": _r(rng.uniform(0.02, 0.06)),
        "max_gain": _r(max_gain),
        "max_analog_gain": _r(min(max_gain, rng.uniform(4.0, 16.0))),
        "start_gain": _r(_loguniform(rng, 1.0, max_gain)),
        "speed": _r(rng.uniform(0.25, 0.6)),
    }
    # ISP.
    rec["defect_threshold"] = _r(rng.uniform(0.02, 0.1))  # share of the raw range above the local median
    rec["demosaic"] = str(rng.choice(["bilinear", "edge_aware"]))
    rec["black_clamp_dn"] = _r(rng.uniform(-0.5, 3.0) * (4 if bits == 12 else 1))  # ISP black a little high
    rec["pedestal_sigma"] = _r(rng.uniform(0.2, 0.9))
    rec["awb"] = {
        "strength": _r(rng.uniform(0.2, 0.6)),
        "max_gain": _r(rng.uniform(1.3, 2.0)),  # AWB cannot leave its Planckian range: sodium cast stays
        "smoothing": _r(rng.uniform(0.6, 0.9)),
    }
    rec["preset_error"] = [_r(rng.normal(1.0, 0.04)), 1.0, _r(rng.normal(1.0, 0.04))]
    rec["saturation"] = _r(rng.uniform(0.75, 1.05))
    rec["crosstalk"] = _r(rng.uniform(0.0, 0.12))
    rec["bloom"] = {
        "threshold": _r(rng.uniform(0.7, 0.95)),
        "strength": _r(rng.uniform(0.05, 0.35)),
        "radius": _r(rng.uniform(0.005, 0.025)),  # share of the frame diagonal
    }
    rec["tnr"] = _r(rng.uniform(0.2, 0.55) if rng.random() < 0.5 else 0.0)
    curve = str(rng.choice(["filmic", "log"]))
    rec["tone"] = {
        "curve": curve,
        "shape": _r(rng.uniform(0.3, 1.2) if curve == "filmic" else rng.uniform(2.0, 6.0)),
        "transfer": str(rng.choice(["srgb", "bt709"])),
        "black_crush": _r(rng.uniform(0.002, 0.012)),
    }
    method = str(rng.choice(["chroma_blur_bilateral", "nlm_luma", "guided"]))
    rec["denoise"] = {
        "method": method,
        "luma": _r(rng.uniform(5.0, 12.0)),
        "chroma_sigma": _r(rng.uniform(1.2, 3.0)),
    }
    rec["sharpen"] = _r(rng.uniform(0.1, 0.7))
    rec["jpeg_quality"] = int(rng.integers(15, 56))
    return rec


def _tone_lut(tone: dict) -> np.ndarray:
    """Linear light to display code: black crush, tone curve, then the sRGB or BT.709 transfer function."""
    x = np.linspace(0.0, 1.0, _LUT_SIZE, dtype=np.float64)
    x = np.clip((x - tone["black_crush"]) / (1.0 - tone["black_crush"]), 0.0, 1.0)
    if tone["curve"] == "filmic":
        k = tone["shape"]  # Reinhard with its white point at 1: lifts shadows by 1 + k, rolls highlights off
        y = x * (1.0 + k) / (1.0 + k * x)
    else:
        a = tone["shape"]  # log curve of video "night modes": stronger shadow lift, flatter highlights
        y = np.log1p(a * x) / np.log1p(a)
    if tone["transfer"] == "srgb":
        v = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    else:
        v = np.where(y < 0.018, 4.5 * y, 1.099 * np.power(y, 0.45) - 0.099)
    return np.clip(v * 255.0, 0.0, 255.0).astype(np.float32)


def _build_look(rec: dict, rng: np.random.Generator, h: int, w: int) -> _Look:
    """Turn the drawn scalars into per-pixel maps for an h x w frame (fixed for the whole sequence)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    diag = math.hypot(h, w)
    illum = np.zeros((h, w, 3), np.float32)
    emit = np.zeros((h, w, 3), np.float32)
    for lt in rec["lights"]:
        cx, cy = lt["x"] * w, lt["y"] * h
        height = lt["spread"] * diag
        d2 = (xx - cx) ** 2 + ((yy - cy) / lt["squash"]) ** 2
        # Cosine-cubed law of a lamp at `height` above the ground plane.
        falloff = (1.0 + d2 / height**2) ** -1.5
        illum += (lt["intensity"] * falloff)[..., None] * _lamp_bgr(lt["lamp"])
        # The lamp hangs `height` above its pool; seen at elevation asin(squash) the pole shortens by cos.
        hx, hy = cx, cy - height * math.sqrt(max(0.0, 1.0 - lt["squash"] ** 2))
        if lt["visible"] and 0 <= hx < w and 0 <= hy < h:
            head = np.exp(-((xx - hx) ** 2 + (yy - hy) ** 2) / (2 * (lt["head_size"] * diag) ** 2))
            # The lamp head is far brighter than anything it lights; it clips and feeds the bloom.
            emit += (head * 40.0 * lt["intensity"])[..., None] * _lamp_bgr(lt["lamp"])
    illum += rec["ambient"] * _lamp_bgr(rec["ambient_light"])
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (diag / 2) ** 2
    vignette = (1.0 - rec["vignetting"] * r2)[..., None]
    illum *= rec["illumination_fraction"] * vignette
    emit *= rec["illumination_fraction"] * vignette

    dark = rec["dark_current_e"] * rng.lognormal(0.0, rec["dsnu"], (h, w))
    hot = rng.random((h, w)) < rec["hot_pixels_per_million"] * 1e-6
    dark[hot] += rng.uniform(30.0, 1500.0, int(hot.sum()))
    prnu = 1.0 + rec["prnu"] * rng.standard_normal((h, w))
    offset = rec["row_fpn_e"] * rng.standard_normal((h, 1)) + rec["col_fpn_e"] * rng.standard_normal((1, w))

    pat = rec["bayer"]
    idx = {"B": 0, "G": 1, "R": 2}
    cfa = np.empty((h, w), np.int8)
    cfa[0::2, 0::2] = idx[pat[0]]
    cfa[0::2, 1::2] = idx[pat[1]]
    cfa[1::2, 0::2] = idx[pat[2]]
    cfa[1::2, 1::2] = idx[pat[3]]

    sy, sx = yy[::4, ::4], xx[::4, ::4]
    meter_w = 1.0 + 2.0 * np.exp(-(((sx - w / 2) / (0.3 * w)) ** 2 + ((sy - h / 2) / (0.3 * h)) ** 2))

    kernel = None
    length = rec["motion_blur_px"]
    if length >= 0.5:
        size = int(math.ceil(length)) * 2 + 1
        kernel = np.zeros((size, size), np.float32)
        c = size // 2
        a = math.radians(rec["motion_angle_deg"])
        for t in np.linspace(-length / 2, length / 2, 4 * size):
            kernel[int(round(c + t * math.sin(a))), int(round(c + t * math.cos(a)))] += 1.0
        kernel /= kernel.sum()
    return _Look(
        record=rec,
        illum=illum,
        emit=emit.astype(np.float32),
        dark_e=dark.astype(np.float32),
        prnu=prnu.astype(np.float32),
        offset_e=offset.astype(np.float32),
        cfa=cfa,
        meter_w=meter_w.astype(np.float32),
        tone_lut=_tone_lut(rec["tone"]),
        motion_kernel=kernel,
    )


_SRGB_TO_LINEAR = np.array(
    [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in np.arange(256) / 255.0], np.float32
)


def _expose(day: np.ndarray, look: _Look, gain: float, rng: np.random.Generator) -> np.ndarray:
    """Scene light through lens and sensor to raw ADC codes (uint16 Bayer mosaic, black level included)."""
    rec = look.record
    scene = _SRGB_TO_LINEAR[day] * look.illum + look.emit
    scene = cv2.GaussianBlur(scene, (0, 0), rec["optics_blur_px"])
    if look.motion_kernel is not None:
        scene = cv2.filter2D(scene, -1, look.motion_kernel, borderType=cv2.BORDER_REFLECT)
    sens = np.asarray(rec["sensor_bgr"], np.float32) * (rec["sensitivity"] * rec["full_well_e"])
    h, w = look.cfa.shape
    flux = np.take_along_axis(scene, look.cfa[..., None].astype(np.intp), axis=2)[..., 0] * sens[look.cfa]
    electrons = rng.poisson(np.maximum(flux * look.prnu + look.dark_e, 0.0)).astype(np.float32)
    electrons = np.minimum(electrons, rec["full_well_e"])
    electrons += rec["read_noise_e"] * rng.standard_normal((h, w), np.float32)
    electrons += look.offset_e + rec["row_noise_e"] * rng.standard_normal((h, 1), np.float32)
    white = 2 ** rec["adc_bits"] - 1
    black = rec["black_level_dn"]
    ae = rec["ae"]
    analog = min(gain, ae["max_analog_gain"])
    digital = gain / analog
    dn_per_e = (white - black) / rec["full_well_e"] * analog
    dn = electrons * dn_per_e + black + rec["adc_noise_dn"] * rng.standard_normal((h, w), np.float32)
    dn = np.clip(np.rint(dn), 0, white)
    if digital > 1.0:  # digital gain after the ADC: stretches the quantisation steps too
        dn = np.clip(np.rint((dn - black) * digital + black), 0, white)
    return dn.astype(np.uint16)


def _meter(raw: np.ndarray, look: _Look) -> float:
    """Centre-weighted mean raw level (0..1 of white), what the auto-exposure loop steers by."""
    rec = look.record
    white = 2 ** rec["adc_bits"] - 1
    sub = (raw[::4, ::4].astype(np.float32) - rec["black_level_dn"]) / (white - rec["black_level_dn"])
    return float(np.sum(np.clip(sub, 0.0, 1.0) * look.meter_w) / np.sum(look.meter_w))


def _guided(img: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """Self-guided filter (He et al.): edge-preserving smoothing in a few box filters."""
    k = (2 * radius + 1, 2 * radius + 1)
    mean = cv2.blur(img, k)
    var = cv2.blur(img * img, k) - mean * mean
    a = var / (var + eps)
    b = mean - a * mean
    return cv2.blur(a, k) * img + cv2.blur(b, k)


class _Isp:
    """The camera's image processor; keeps white-balance and temporal-denoise state from frame to frame."""

    def __init__(self, look: _Look) -> None:
        self.look = look
        self.rec = look.record
        self.awb: np.ndarray | None = None
        self.prev: np.ndarray | None = None
        rec = self.rec
        s = rec["saturation"]
        desat = s * np.eye(3) + (1.0 - s) * np.tile(_LUMA_BGR, (3, 1))
        c = rec["crosstalk"]  # a CCM that over/under-corrects sensor crosstalk a little; rows keep white white
        cross = (1.0 + c) * np.eye(3) - c / 2 * (np.ones((3, 3)) - np.eye(3))
        self.ccm = (desat @ cross).astype(np.float32)
        rec["ccm_bgr"] = [[_r(v) for v in row] for row in self.ccm]

    def __call__(self, raw: np.ndarray, gain: float) -> np.ndarray:
        rec = self.rec
        h, w = raw.shape
        raw = self._correct_defects(raw)
        code = (_BAYER_EA if rec["demosaic"] == "edge_aware" else _BAYER)[rec["bayer"]]
        rgb = cv2.cvtColor(raw, code).astype(np.float32)
        white = 2 ** rec["adc_bits"] - 1
        black = rec["black_level_dn"] + rec["black_clamp_dn"]
        # Kept signed until the tone curve, so that averaging (AWB, TNR) does not lift the noise floor.
        lin = (rgb - black) / (white - rec["black_level_dn"])
        # Daylight preset undoes the sensor's channel response (with a calibration error) ...
        preset = np.asarray(rec["preset_error"], np.float32) / np.asarray(rec["sensor_bgr"], np.float32)
        lin *= preset
        # ... then grey-world AWB removes only part of the lamp cast, within the gains it is allowed.
        means = np.maximum(lin.reshape(-1, 3)[::7].mean(axis=0), 1e-5)
        awb = rec["awb"]
        gains = np.clip((means[1] / means) ** awb["strength"], 1.0 / awb["max_gain"], awb["max_gain"])
        sm = awb["smoothing"]
        self.awb = gains if self.awb is None else sm * self.awb + (1.0 - sm) * gains
        lin *= self.awb.astype(np.float32)
        lin = cv2.transform(lin, self.ccm)
        # Bloom: light above the clip level spreads into a halo (lens glare and sensor blooming).
        bl = rec["bloom"]
        excess = np.maximum(lin - bl["threshold"], 0.0)
        if excess.any():
            sigma = bl["radius"] * math.hypot(h, w)
            small = cv2.resize(excess, (max(1, w // 4), max(1, h // 4)), interpolation=cv2.INTER_AREA)
            small = cv2.GaussianBlur(small, (0, 0), max(0.5, sigma / 4))
            lin += bl["strength"] * cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        lin = np.minimum(lin, 1.0)
        # Motion-adaptive temporal noise reduction: blends in the last frame where little changed (ghosts on motion).
        if rec["tnr"] > 0 and self.prev is not None:
            diff = np.abs(lin - self.prev).mean(axis=2, keepdims=True)
            alpha = rec["tnr"] * np.exp(-((diff / 0.02) ** 2))
            lin = lin * (1.0 - alpha) + self.prev * alpha
        self.prev = lin
        # Gain-indexed black pedestal: the ISP knows its read-noise floor at this gain and cuts part of it off,
        # which is why night footage has crushed, nearly noise-free blacks.
        ped = rec["pedestal_sigma"] * rec["read_noise_e"] * gain / rec["full_well_e"]
        lin = np.clip((lin - ped) / (1.0 - ped), 0.0, 1.0)
        disp = self.look.tone_lut[(lin * (_LUT_SIZE - 1)).astype(np.int32)]
        out = self._denoise_sharpen(np.clip(disp + 0.5, 0, 255).astype(np.uint8), gain)
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, rec["jpeg_quality"]])
        if not ok:  # pragma: no cover - imencode of a valid uint8 image does not fail
            return out
        return cv2.imdecode(buf, cv2.IMREAD_COLOR)

    def _correct_defects(self, raw: np.ndarray) -> np.ndarray:
        """Dynamic defect-pixel correction: photosites far above their same-colour neighbours take the median.

        Hot pixels below the threshold survive, as they do in cheap cameras."""
        rec = self.rec
        thr = rec["defect_threshold"] * (2 ** rec["adc_bits"] - 1 - rec["black_level_dn"])
        raw = raw.copy()
        for dy in (0, 1):
            for dx in (0, 1):
                plane = np.ascontiguousarray(raw[dy::2, dx::2])
                med = cv2.medianBlur(plane, 3)
                bad = plane.astype(np.float32) > med.astype(np.float32) + thr
                plane[bad] = med[bad]
                raw[dy::2, dx::2] = plane
        return raw

    def _denoise_sharpen(self, img: np.ndarray, gain: float) -> np.ndarray:
        """YCrCb-domain noise reduction (chroma smeared, luma edge-aware) and an unsharp mask on luma."""
        dn = self.rec["denoise"]
        # Like a real ISP's gain-indexed tuning table: the higher the gain, the harder the noise reduction.
        strength = dn["luma"] * min(4.0, max(1.0, math.sqrt(gain / 2.0)))
        ycc = cv2.cvtColor(img, cv2.COLOR_BGR2YCrCb)
        y = ycc[..., 0]
        chroma = cv2.GaussianBlur(ycc[..., 1:], (0, 0), dn["chroma_sigma"])
        if dn["method"] == "nlm_luma":
            y = cv2.fastNlMeansDenoising(y, None, strength, 3, 7)
        elif dn["method"] == "guided":
            yf = y.astype(np.float32) / 255.0
            y = np.clip(_guided(yf, 2, (strength / 255.0) ** 2 * 2.0) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        else:
            y = cv2.bilateralFilter(y, 7, strength * 2.5, 2.5)
        yf = y.astype(np.float32)
        yf += self.rec["sharpen"] * (yf - cv2.GaussianBlur(yf, (0, 0), 1.2))
        ycc = np.dstack([np.clip(yf + 0.5, 0, 255).astype(np.uint8), chroma])
        return cv2.cvtColor(ycc, cv2.COLOR_YCrCb2BGR)


def render_night(day: list[np.ndarray], seed: list[int]) -> tuple[list[np.ndarray], dict]:
    """Render a day sequence as this camera would have filmed it at night.

    day: BGR uint8 frames of one size. seed: non-negative ints; the same day and seed give the same night.
    Returns the night frames (BGR uint8, same size) and a JSON-serialisable record of every drawn parameter, so a
    result can be traced to the look that produced it.
    """
    if len(day) == 0:
        return [], {"model": MODEL, "seed": list(seed) if not isinstance(seed, int) else [seed], "n_frames": 0}
    first = day[0]
    for i, f in enumerate(day):
        if not isinstance(f, np.ndarray) or f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
            raise ValueError(
                f"frame {i} must be a BGR uint8 array, got {getattr(f, 'dtype', type(f))} {getattr(f, 'shape', None)}"
            )
        if f.shape != first.shape:
            raise ValueError(
                f"frame {i} has size {f.shape[1]}x{f.shape[0]}, frame 0 has {first.shape[1]}x{first.shape[0]}"
            )
    seeds = [int(seed)] if isinstance(seed, (int, np.integer)) else [int(s) for s in seed]
    # Separate streams: scalars, per-pixel maps, per-frame noise. The look then does not depend on frame size or
    # sequence length, and each frame's noise is fresh but reproducible.
    param_ss, map_ss, noise_ss = np.random.SeedSequence(seeds).spawn(3)
    rec = _draw_record(np.random.default_rng(param_ss))
    h, w = first.shape[:2]
    look = _build_look(rec, np.random.default_rng(map_ss), h, w)
    isp = _Isp(look)
    ae = rec["ae"]
    gain = ae["start_gain"]
    gains = []
    out = []
    for frame, ss in zip(day, noise_ss.spawn(len(day)), strict=True):
        raw = _expose(np.ascontiguousarray(frame), look, gain, np.random.default_rng(ss))
        gains.append(_r(gain))
        out.append(isp(raw, gain))
        level = _meter(raw, look)
        gain = float(np.clip(gain * (ae["target"] / max(level, 1e-5)) ** ae["speed"], 1.0, ae["max_gain"]))
    rec = dict(rec)
    rec["seed"] = seeds
    rec["size"] = [w, h]
    rec["n_frames"] = len(day)
    rec["gain_per_frame"] = gains
    return out, rec

