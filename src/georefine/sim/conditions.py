"""Operating conditions of a simulated corridor flight: the levels of the scenario matrix.

The factors and their levels as ``--set`` overrides on top of a scenario (``bench/scenario_matrix.py``
runs every combination or one at a time on ``corridor``; ``tests/test_operating_matrix.py`` a
covering selection on ``corridor-tiny``):

| factor | levels |
|---|---|
| IMU grade | mems (STIM300), tactical (HG1700), navigation (HG9900): ``--imu-grade`` |
| flight | slow-low: the scenario's (18 m/s at 160 m AGL, 100 kHz); fast-high: 30 m/s at 300 m AGL, 300 kHz |
| GNSS | ppk-5hz (the simulator's default); ppk-1hz: 1 Hz with twice the white and correlated errors; outage: GNSS lost and regained inside pass 1 (:func:`~georefine.sim.scenarios.outage_inside_pass`) |
| latitude | mid (46.7 N, EPSG:25832), south (33.9 S, EPSG:32734), high (69.6 N, EPSG:32634) |
| vibration | off, on (rotor harmonics at 6.5/13/26 Hz) |
"""

from __future__ import annotations

from georefine.errors import ConfigError
from georefine.sim.scenarios import ScenarioConfig, outage_inside_pass, resolve_scenario

__all__ = ["FLIGHT", "GNSS", "IMU", "LATITUDE", "VIBRATION", "condition_overrides"]

IMU = ("mems", "tactical", "navigation")
FLIGHT = {
    "slow-low": [],
    "fast-high": ["flight.altitude_agl_m=300", "flight.speed_mps=30", "scanner.pulse_rate_hz=300000"],
}
GNSS = {
    "ppk-5hz": [],
    "ppk-1hz": ["gnss.rate_hz=1", "gnss.sigma_north_m=0.02", "gnss.sigma_east_m=0.02", "gnss.sigma_up_m=0.04",
                "gnss.gm_sigma_horizontal_m=0.03", "gnss.gm_sigma_up_m=0.06"],
    "outage": None,  # inside pass 1: from the flight plan (condition_overrides)
}
LATITUDE = {
    "mid": [],
    "south": ["reference_point.lat_deg=-33.9", "reference_point.lon_deg=18.6", "reference_point.h_m=100",
              "output_epsg=32734"],
    "high": ["reference_point.lat_deg=69.6", "reference_point.lon_deg=18.9", "reference_point.h_m=50",
             "output_epsg=32634"],
}
VIBRATION = {"off": [], "on": ["flight.vibration.enabled=true"]}


def condition_overrides(scenario: str, imu: str, flight: str, gnss: str, latitude: str, vibration: str, seed: int,
                        base: list[str] | None = None, outage_s: tuple[float, float, float] = (10.0, 60.0, 10.0)
                        ) -> list[str]:
    """The ``--set`` overrides of one combination of levels on ``scenario`` (after ``base``).

    ``outage_s``: (start after the pass begins, longest length, margin before it ends) of the
    ``outage`` level, in seconds.

    Raises
    ------
    ConfigError
        An unknown level, or a pass too short for the outage.
    """
    for factor, level, levels in (("imu", imu, IMU), ("flight", flight, FLIGHT), ("gnss", gnss, GNSS),
                                  ("latitude", latitude, LATITUDE), ("vibration", vibration, VIBRATION)):
        if level not in levels:
            raise ConfigError("unknown level", field=factor, expected="one of " + ", ".join(levels), found=repr(level))
    overrides = [*(base or []), *FLIGHT[flight], *LATITUDE[latitude], *VIBRATION[vibration]]
    if gnss == "outage":
        cfg: ScenarioConfig = resolve_scenario(scenario, seed_overrides=overrides, imu_grade=imu)
        start, length, margin = outage_s
        return [*overrides, outage_inside_pass(cfg, seed, start_after_s=start, length_s=length, margin_s=margin)]
    return [*overrides, *GNSS[gnss]]
