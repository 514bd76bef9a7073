"""The position estimator: pure numpy over skyline arrays; no files, devices or logs."""

from appliance.estimator.estimate import EstimateResult, FirstPass, SkylineGrid, estimate, first_pass, resample_to_grid
from appliance.estimator.exact import PositionPrior
from appliance.estimator.fusion import transport_fix, transport_prior

__all__ = ["EstimateResult", "FirstPass", "SkylineGrid", "estimate", "first_pass", "resample_to_grid",
           "transport_prior", "transport_fix", "PositionPrior"]
