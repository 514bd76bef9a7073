"""The position estimator: pure numpy over skyline arrays; no files, devices or logs."""

from appliance.estimator.coarse import FirstPass
from appliance.estimator.estimate import EstimateResult, estimate, first_pass
from appliance.estimator.exact import PositionPrior
from appliance.estimator.fusion import transport_fix, transport_prior
from appliance.estimator.measurement import resample_to_grid
from appliance.estimator.skyline_grid import COARSE_STRIDE, SkylineGrid, first_pass_ahead

__all__ = ["EstimateResult", "FirstPass", "SkylineGrid", "estimate", "first_pass", "resample_to_grid",
           "transport_prior", "transport_fix", "PositionPrior", "COARSE_STRIDE", "first_pass_ahead"]
