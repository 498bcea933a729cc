"""One scale error shared by every stereo VO step of the traverse.

A stereo baseline known to 0.5 % makes every VO step 0.5 % too long or too short, the same
way at every step (the seed's field VO "came out shorter than GPS"); treated as independent per
step, that error grows with N while the covariance grows with sqrt(N). Here S(1) is a variable
with prior N(0, [estimator.vo_scale] sigma), and every VO between factor becomes a factor on its two poses
and S(1) (the wheel-slip kind's factor: measured translation = (1 + scale) x true); GPS or
site tie points, where present, estimate it.
"""

from __future__ import annotations

import gtsam
from pydantic import Field

from ..graph.keys import S
from ..sections import Section
from .base import Kind
from .motion import VisualOdometry
from .wheel_slip import slip_odometry_factor

VO_SCALE = S(1)


def vo_scale_factor(key_a: int, key_b: int, vo_T: gtsam.Pose3, covariance):
    return slip_odometry_factor(key_a, key_b, vo_T, covariance, scale_key=VO_SCALE)


class VoScaleSettings(Section):
    """[estimator.vo_scale]"""

    sigma: float = Field(0.01, gt=0.0, lt=0.5, description="1-sigma scale error shared by every VO step (the "
                         "stereo baseline's calibration)")


class VoScale(Kind):
    name = "vo_scale"
    order = 6
    Settings = VoScaleSettings
    unavailable = staticmethod(VisualOdometry.unavailable)

    def __init__(self, localizer):
        super().__init__(localizer)
        model = gtsam.noiseModel.Isotropic.Sigma(1, localizer.estimator.vo_scale.sigma)
        localizer.smoother.add(gtsam.PriorFactorDouble(VO_SCALE, 0.0, model))
        localizer.smoother.insert(VO_SCALE, 0.0, shared=True)
        localizer.vo_factor = vo_scale_factor

    def true_values(self, truth, values: gtsam.Values) -> bool:
        # the calibration's scale error: zero in simulation, unknown on real data, where the bound
        # is linearized at its prior mean (the factor is nearly linear in it)
        values.insert(VO_SCALE, 0.0)
        return True

    def counters(self) -> dict:
        scale = self.loc.smoother.estimate_double(VO_SCALE)
        sigma = float(self.loc.smoother.marginal_covariance(VO_SCALE)[0, 0] ** 0.5)
        return {"vo_scale": scale, "vo_scale_sigma": sigma}
