"""Unit grades for `gyrocal sim --grade`: a fibre-optic gyro, a tactical MEMS part, a consumer MEMS part.

The calibrator must work for any unit that follows docs/protocol.md, whose noise may be 250 times
that of the demo's. A grade sets what differs between such units:

- ``noise_density_dps_rthz``: white rate noise (angle random walk) [deg/s/sqrt(Hz)]. The noise per
  sample is density x sqrt(rate), so a unit sampled faster is noisier per sample, as a real part is.
- ``gravity_scale``: the gravity-dependent drift, as a multiple of seed 000 Table 1 (deg/h, deg/h/g,
  deg/h/g^2). MEMS parts have a g-sensitivity tens of times that of the paper's gyro.
- ``switch_on_bias_dph``: the std of the bias drawn anew at every switch-on [deg/h].
- ``temp_dph_per_c``: the bias slope on temperature [deg/h per degC]; with ``thermal_rise_c`` of
  warm-up after switch-on (time constant ``thermal_tau_s``).
- ``bias_instability_dph``: the bias instability B [deg/h], the flicker floor of the Allan deviation
  (0.664 B over 1..1000 s), rendered by sim/truth.py's flicker (``Effects.bias_instability_dps``).
- ``rate_random_walk_dps_rts``: bias random walk [deg/s/sqrt(s)], rendered by the truth model.
- ``accel_noise_density_g_rthz``: accelerometer white noise [g/sqrt(Hz)].

The figures are typical datasheet values, not any one part's: fibre ~ a navigation-grade FOG
(ARW 0.004 deg/sqrt(h)), tactical ~ an ADIS1649x-class IMU (ARW 0.09 deg/sqrt(h)), consumer ~ an
MPU-6050-class part (ARW 0.3 deg/sqrt(h); 0.16 deg/s per sample at 1 kHz, like the issue's unit).
``demo`` is the demo's unit exactly (seed 000's drift, 0.002 deg/s per sample whatever the rate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gyrocal.sim.truth import DPH, Effects, Thermal, TruthModel, default_coefficients_dps


@dataclass(frozen=True)
class Grade:
    name: str
    noise_density_dps_rthz: float | None
    """White rate noise [deg/s/sqrt(Hz)]; None = the demo's fixed 0.002 deg/s per sample."""
    gravity_scale: float
    switch_on_bias_dph: float
    temp_dph_per_c: float
    thermal_rise_c: float
    thermal_tau_s: float
    rate_random_walk_dps_rts: float
    bias_instability_dph: float
    """Bias instability B [deg/h] (flicker; the Allan floor is 0.664 B)."""
    accel_noise_density_g_rthz: float
    description: str

    def noise_per_sample_dps(self, rate_hz: float) -> float:
        if self.noise_density_dps_rthz is None:
            return 0.002
        return self.noise_density_dps_rthz * float(np.sqrt(rate_hz))

    def truth(self, rate_hz: float) -> TruthModel:
        """The truth model of a unit of this grade sampled at ``rate_hz`` [Hz]."""
        if self.name == "demo":
            return TruthModel()
        return TruthModel(
            coeffs_dps=default_coefficients_dps() * self.gravity_scale,
            switch_on_bias_dps=self.switch_on_bias_dph * DPH,
            noise_dps=self.noise_per_sample_dps(rate_hz),
            accel_noise_g=self.accel_noise_density_g_rthz * float(np.sqrt(rate_hz)),
            thermal=Thermal(rise_c=self.thermal_rise_c, tau_s=self.thermal_tau_s),
            effects=Effects(temp_dps_per_c=np.full(3, self.temp_dph_per_c * DPH),
                            random_walk_dps_per_sqrt_s=np.full(3, self.rate_random_walk_dps_rts),
                            bias_instability_dps=np.full(3, self.bias_instability_dph * DPH)),
        )


GRADES: dict[str, Grade] = {
    "demo": Grade("demo", None, 1.0, 36.0, 0.0, 8.0, 120.0, 0.0, 0.0, 2e-4 / np.sqrt(1000.0),
                  "the demo's unit: seed 000 drift, 0.002 deg/s per sample"),
    "fibre": Grade("fibre", 6e-5, 1.0, 10.0, 0.05, 2.0, 300.0, 0.0, 0.005, 2e-6,
                   "navigation-grade fibre-optic gyro: ARW 0.004 deg/sqrt(h)"),
    "tactical": Grade("tactical", 1.5e-3, 10.0, 180.0, 0.5, 2.0, 300.0, 0.0, 0.8, 2e-5,
                      "tactical MEMS IMU: ARW 0.09 deg/sqrt(h), 70 deg/h/g"),
    "consumer": Grade("consumer", 5e-3, 40.0, 1800.0, 5.0, 2.0, 300.0, 0.0, 10.0, 1e-4,
                      "consumer MEMS part: ARW 0.3 deg/sqrt(h), 300 deg/h/g, 0.5 deg/s switch-on bias"),
}


def grade(name: str) -> Grade:
    try:
        return GRADES[name]
    except KeyError:
        raise ValueError(f"unknown unit grade {name!r}; pick one of {', '.join(GRADES)}") from None


def grade_truth(name: str, rate_hz: float = 1000.0) -> TruthModel:
    return grade(name).truth(rate_hz)
