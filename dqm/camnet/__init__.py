"""The camera-network experiment of the seed paper, in simulation.

Five cameras at known poses watch a textured box-shaped target drive a loop;
each camera detects the target by matching SIFT features against the target's
reference images (QuickMatch over all images of a time step, or BF / FLANN
pairwise with Lowe's ratio test; QuickMatch also with the quadratic kernel,
and online: one clustering updated frame by frame) and localizes it from the
bounding box of a RANSAC homography. Modules:

* :mod:`~dqm.camnet.geometry` - cameras, projection, box -> distance / bearing -> position;
* :mod:`~dqm.camnet.simulator` - the seeded world and its renderer with exact ground truth;
* :mod:`~dqm.camnet.pipeline` - matching, detection and localization per time step;
* :mod:`~dqm.camnet.online` - online QuickMatch fed one camera frame at a time;
* :mod:`~dqm.camnet.experiment` - the whole run and its scores (PR curves, errors);
* :mod:`~dqm.camnet.summary` - every number and finding, computed once (the JSON and the markdown read it).
* :mod:`~dqm.camnet.report` - figures, and the JSON and markdown rendered from the summary.

Command line: ``dqm experiment localization`` (see ``dqm experiment --help``).
"""
from .experiment import (
                         ExperimentResult,
                         common_errors,
                         detection_curve,
                         localization_errors,
                         operating_point,
                         run_experiment,
)
from .geometry import Camera, Intrinsics
from .pipeline import METHODS, PipelineConfig
from .simulator import SimConfig, World, build_world

__all__ = [
    "Camera", "ExperimentResult", "Intrinsics", "METHODS", "PipelineConfig", "SimConfig", "World",
    "build_world", "common_errors", "detection_curve", "localization_errors", "operating_point",
    "run_experiment",
]
