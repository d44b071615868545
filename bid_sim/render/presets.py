"""Weather presets for the renderer: sun, sky and light colours, fog, wet roads and rain.

Weather changes only pixels, never the traffic. Colours are RGB 0–255.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bid_sim.weather import WEATHERS, check_weather


@dataclass(frozen=True)
class WeatherPreset:
    name: str
    sky_top: tuple[int, int, int]
    sky_horizon: tuple[int, int, int]  # also the fog colour
    sun_elevation_deg: float
    sun_azimuth_deg: float  # world frame, counter-clockwise from +x (east)
    light: tuple[float, float, float]  # sunlight colour, multiplies lit surfaces
    ambient: float  # share of light on faces turned away from the sun
    diffuse: float  # share that follows the sun direction
    fog_start_m: float  # fog ramps from 0 here ...
    fog_full_m: float  # ... to fog_max here (also the view range for objects)
    fog_max: float
    wet: float  # 0 dry – 1 soaked: darker ground, sky sheen at grazing angles, reflections
    rain: float  # 0 none – 1 hard: rain streaks
    ground_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def sun_vector(self) -> np.ndarray:
        """Unit vector towards the sun (world frame)."""
        el, az = math.radians(self.sun_elevation_deg), math.radians(self.sun_azimuth_deg)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

    def fog(self, dist_m: np.ndarray | float) -> np.ndarray:
        """Share of fog colour (0–fog_max) at a distance: a smooth ramp."""
        t = np.clip((np.asarray(dist_m, dtype=np.float64) - self.fog_start_m)
                    / (self.fog_full_m - self.fog_start_m), 0.0, 1.0)
        return self.fog_max * t * t * (3.0 - 2.0 * t)


_NOON = {"sky_top": (70, 130, 205), "sky_horizon": (178, 204, 230), "sun_elevation_deg": 60.0,
         "sun_azimuth_deg": 130.0, "light": (1.0, 1.0, 0.97), "ambient": 0.55, "diffuse": 0.5}
_SUNSET = {"sky_top": (60, 78, 140), "sky_horizon": (236, 164, 110), "sun_elevation_deg": 9.0,
           "sun_azimuth_deg": 200.0, "light": (1.0, 0.74, 0.5), "ambient": 0.5, "diffuse": 0.62}

PRESETS: dict[str, WeatherPreset] = {
    "ClearNoon": WeatherPreset("ClearNoon", **_NOON, fog_start_m=45.0, fog_full_m=110.0,
                               fog_max=1.0, wet=0.0, rain=0.0),
    "WetNoon": WeatherPreset("WetNoon", **{**_NOON, "sky_top": (96, 140, 196)}, fog_start_m=40.0,
                             fog_full_m=105.0, fog_max=1.0, wet=0.75, rain=0.0),
    "HardRainNoon": WeatherPreset("HardRainNoon", sky_top=(92, 98, 108), sky_horizon=(150, 154, 160),
                                  sun_elevation_deg=60.0, sun_azimuth_deg=130.0,
                                  light=(0.86, 0.88, 0.92), ambient=0.72, diffuse=0.18,
                                  fog_start_m=8.0, fog_full_m=75.0, fog_max=1.0, wet=1.0, rain=1.0,
                                  ground_tint=(0.92, 0.94, 0.97)),
    "ClearSunset": WeatherPreset("ClearSunset", **_SUNSET, fog_start_m=40.0, fog_full_m=105.0,
                                 fog_max=1.0, wet=0.0, rain=0.0, ground_tint=(1.0, 0.9, 0.8)),
    "WetSunset": WeatherPreset("WetSunset", **_SUNSET, fog_start_m=35.0, fog_full_m=100.0,
                               fog_max=1.0, wet=0.8, rain=0.0, ground_tint=(0.98, 0.88, 0.8)),
    "SoftRainSunset": WeatherPreset("SoftRainSunset", **{**_SUNSET, "sky_top": (84, 84, 116),
                                    "sky_horizon": (196, 150, 120), "ambient": 0.55, "diffuse": 0.4},
                                    fog_start_m=15.0, fog_full_m=90.0, fog_max=1.0, wet=0.7,
                                    rain=0.45, ground_tint=(0.96, 0.88, 0.82)),
}
assert set(PRESETS) == set(WEATHERS)


def preset(weather: str | WeatherPreset) -> WeatherPreset:
    """The preset for a weather name (BidError naming the choices for an unknown one)."""
    if isinstance(weather, WeatherPreset):
        return weather
    return PRESETS[check_weather(weather)]
