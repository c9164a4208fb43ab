"""Metric fits with an error model (beyond the paper): the backbone's positions regressed on the IMU kinematics over
one clip or a window of clips, the named layout of their unknowns, Gaussian priors and sliding-window
marginalisation, and the paper's position fit for a known gravity and velocity. The initialisation (``init``) and
the online window (``online``) both solve with these."""

from vi3_core.fit.layout import PriorLayout, StateLayout
from vi3_core.fit.marginalise import marginalise
from vi3_core.fit.metric_fit import FitClip, FitResult, FitState, MetricFit, ScaleLink, fit_stamps
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.fit.prior import GaussianPrior

__all__ = ["FitClip", "FitResult", "FitState", "GaussianPrior", "ImuNoiseModel", "MetricFit", "PriorLayout",
           "ScaleLink", "StateLayout", "fit_stamps", "marginalise"]
