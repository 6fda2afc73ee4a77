"""The camera model: how a DAVIS turns the scene's light into APS values and sets its event thresholds, and
the named realistic effects with their documented DAVIS240/346 values and sources.

Each effect is off by default (its SceneConfig fields at their neutral values). `with_effects(cfg, name...)`
switches effects on; an effect fills in its values only for parameters still at SceneConfig's defaults, so
settings made explicitly win. `true_camera(sim)` is what an oracle may know about the simulated camera.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from edi_live.simulation.config import PRESETS, SceneConfig

_DEFAULTS = SceneConfig()


@dataclass(frozen=True)
class Effect:
    """One realistic camera effect: which SceneConfig fields it sets, to what, and where the values come from."""

    name: str
    what: str
    source: str
    settings: Callable[[SceneConfig], dict]


def _hot_count(cfg: SceneConfig) -> int:
    return max(1, round(3e-4 * cfg.width * cfg.height))


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("black_level", "APS black level: 10 DN added to every APS value before rounding",
           "size used by the team's real-camera notes (sec. 2); DV's 8-bit output of our three DAVIS346 "
           "recordings reaches 0 DN, i.e. most of the offset is removed there: 10 DN is an uncorrected residue",
           lambda c: {"aps_offset_dn": 10.0}),
    Effect("response", "non-linear APS response 255*(I/255)**(1/1.15)",
           "fast_EDI ships a calibrated non-linear DAVIS346 response curve; gamma 1.15 as in the real-camera notes",
           lambda c: {"aps_gamma": 1.15}),
    Effect("read_noise", "APS temporal (read + shot) noise, Gaussian, 1 DN RMS before 8-bit rounding",
           "iniVation DAVIS346 specification: APS dynamic range 55 dB, i.e. a noise floor of 255/10^(55/20) = "
           "0.45 DN at 8 bits; photon shot noise at mid grey roughly doubles it",
           lambda c: {"aps_noise_dn": 1.0}),
    Effect("clock_offset", "event timestamps 1.5 ms late against the APS exposure window",
           "EDI authors' t_shift (-20 to -40 ms, 'set experimentally', EDI repo issue #5); pixel latency of "
           "microseconds to milliseconds by light level (iniVation biasing guide); 1.5 ms as in issue 10",
           lambda c: {"event_offset_us": 1500}),
    Effect("thresholds", "c_off = 0.8 c_on and a per-pixel Gaussian threshold spread of 0.05 (log units)",
           "ON and OFF thresholds come from separate biases (iniVation biasing guide); fast_EDI's DAVIS346 "
           "defaults c_pos=0.2609, c_neg=0.2415 differ; v2e's 'noisy' DVS uses sigma 0.05 (its default 0.03)",
           lambda c: {**({"c_off": round(0.8 * c.c_on, 6)} if c.c_off == c.c_on else {}),
                      **({"c_sigma": 0.05} if c.c_sigma == _DEFAULTS.c_sigma else {})}),
    Effect("refractory", "a refractory period of 0.5 ms after each event of a pixel",
           "v2e's default refractory period (0.5 ms); the refractory bias of the iniVation biasing guide",
           lambda c: {"refractory_us": 500}),
    Effect("background", "background activity: 0.1 Hz per pixel in any light, plus up to 5 Hz in the dark",
           "iniVation biasing guide and the real-camera notes: about 0.1 Hz/pixel in normal light, more in the "
           "dark; v2e's 'noisy' DVS: leak 0.1 Hz, shot noise 5 Hz. Rate here: 0.1 + 5*min(1, 0.1/I) Hz",
           lambda c: {"noise_rate_hz": 0.1, "shot_noise_hz": 5.0}),
    Effect("hot_pixels", "3 in 10,000 pixels fire at 150 Hz regardless of the scene",
           "our DAVIS346 recordings (evlib sample: 29 of 90k pixels above 100 Hz, the busiest at ~150 Hz)",
           lambda c: {"hot_pixels": _hot_count(c), "hot_rate_hz": 150.0}),
    Effect("flicker", "a lamp (a disk in the scene) modulated at 100 Hz, depth 0.4",
           "50 Hz mains make lamps flicker at 100 Hz (120 Hz on 60 Hz mains); the aestream DAVIS346 recording "
           "shows dense ON/OFF bursts on its ceiling lamps",
           lambda c: {"flicker_hz": 100.0}),
)}


def with_effects(cfg: SceneConfig, *names: str) -> SceneConfig:
    """cfg with the named effects on ("all" = every one). A parameter you already changed from SceneConfig's
    default keeps your value; the thresholds effect sets c_off only while c_off == c_on."""
    expanded: list[str] = []
    for n in names:
        if n == "all":
            expanded += list(EFFECTS)
        elif n in EFFECTS:
            expanded.append(n)
        else:
            raise ValueError(f"unknown camera effect {n!r}; choose from {sorted(EFFECTS)} or 'all'")
    for n in expanded:
        wanted = EFFECTS[n].settings(cfg)
        keep = {k: v for k, v in wanted.items()
                if k in ("c_off", "c_sigma") or getattr(cfg, k) == getattr(_DEFAULTS, k)}
        record = cfg.effects if n in cfg.effects else cfg.effects + (n,)
        cfg = dataclasses.replace(cfg, **keep, effects=record)
    return cfg


def threshold_maps(cfg: SceneConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ON and OFF thresholds (flat float32): mean c plus Gaussian mismatch, floored above zero."""
    n = cfg.width * cfg.height
    floor_c = lambda c: max(0.25 * c, 0.01)  # noqa: E731 - a mismatch draw never makes a threshold vanish
    con = np.maximum(cfg.c_on + cfg.c_sigma * rng.standard_normal(n), floor_c(cfg.c_on)).astype(np.float32)
    coff = np.maximum(cfg.c_off + cfg.c_sigma * rng.standard_normal(n), floor_c(cfg.c_off)).astype(np.float32)
    return con, coff


def aps_values(cfg: SceneConfig, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The 8-bit APS frame from the exposure's mean linear intensity (0..255): response, black level, read
    noise, rounding and clipping, in the order a sensor applies them."""
    img = linear.astype(np.float64)
    if cfg.aps_gamma != 1.0:
        img = 255.0 * (img / 255.0) ** (1.0 / cfg.aps_gamma)
    img = img + cfg.aps_offset_dn
    if cfg.aps_noise_dn > 0:
        img = img + cfg.aps_noise_dn * rng.standard_normal(img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def linearise_aps(cfg: SceneConfig | dict, image: np.ndarray) -> np.ndarray:
    """The inverse of `aps_values` without noise: APS DN -> linear intensity on 0..255 (float64)."""
    get = cfg.get if isinstance(cfg, dict) else lambda k: getattr(cfg, k)
    img = np.clip(np.asarray(image, np.float64) - float(get("aps_offset_dn")), 0.0, None)
    gamma = float(get("aps_gamma"))
    return 255.0 * (img / 255.0) ** gamma if gamma != 1.0 else img


def true_camera(cfg: SceneConfig, c_on_map: np.ndarray, c_off_map: np.ndarray, hot_pixel_xy: np.ndarray) -> dict:
    """Everything about the simulated camera an oracle may use (scalars and the per-pixel maps)."""
    return {"c_on": cfg.c_on, "c_off": cfg.c_off, "c_sigma": cfg.c_sigma, "c_on_map": c_on_map,
            "c_off_map": c_off_map, "event_offset_us": cfg.event_offset_us, "aps_offset_dn": cfg.aps_offset_dn,
            "aps_gamma": cfg.aps_gamma, "aps_noise_dn": cfg.aps_noise_dn, "refractory_us": cfg.refractory_us,
            "noise_rate_hz": cfg.noise_rate_hz, "shot_noise_hz": cfg.shot_noise_hz,
            "shot_noise_dark": cfg.shot_noise_dark, "hot_pixel_xy": hot_pixel_xy, "hot_rate_hz": cfg.hot_rate_hz,
            "flicker_hz": cfg.flicker_hz, "flicker_depth": cfg.flicker_depth, "flicker_level": cfg.flicker_level,
            "flicker_region": tuple(cfg.flicker_region), "effects": tuple(cfg.effects)}


def preset(name: str, *, effects: tuple[str, ...] | list[str] = (), **overrides) -> SceneConfig:
    """A named scene (see config.PRESETS) with keyword overrides, then camera effects switched on, e.g.
    preset("translate", c_on=0.3, effects=("flicker",)). Effects fill in their documented values only
    for parameters still at SceneConfig's defaults: what you set explicitly wins."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    base = dict(PRESETS[name])
    names = tuple(base.pop("effects", ())) + tuple(effects)
    cfg = dataclasses.replace(SceneConfig(**base), **overrides)
    return with_effects(cfg, *names) if names else cfg
