"""GT-free inertial initialisation (paper Sec. "Inertial state initialization"), like OpenVINS' ``ov_init``:
options, data checks, gyro bias, scale/gravity/velocity, gravity seeds, the facade, and the GT oracle."""

from vi3_core.init.initializer import initialise, initialise_clip
from vi3_core.init.options import InitOptions
from vi3_core.init.oracle import oracle_init

__all__ = ["InitOptions", "initialise", "initialise_clip", "oracle_init"]
