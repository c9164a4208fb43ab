"""Exception types of ``vi3_core``: each names the offending input and what is wrong with it."""

from __future__ import annotations


class Vi3Error(Exception):
    """Base class of every error raised on purpose by vi3_core."""


class DataError(Vi3Error, ValueError):
    """Input data (images, IMU, stamps, files) is malformed or inconsistent."""


class CalibrationError(DataError):
    """Camera intrinsics, distortion or camera-IMU extrinsics are missing or invalid."""


class BackboneUnavailable(Vi3Error, ImportError):
    """A backbone's upstream package or checkpoint is not installed; the message says how to get it."""


class ModeNotSupported(Vi3Error):
    """A backbone was asked for an anchoring mode it cannot do (e.g. conditioning on a model without it)."""


class DeviceUnavailable(Vi3Error):
    """The torch device asked for does not exist here (no CUDA, no such GPU, a malformed name)."""


class ClusterUnavailable(Vi3Error):
    """A distributed evaluation cannot run: Ray is not installed, its cluster cannot be reached, has too few
    resources for one worker, or a worker cannot build the backbone; the message says which and what to do."""


def yaml_problem(err: Exception) -> str:
    """A PyYAML error (``yaml.YAMLError``) in one line for a message after the file's name: "line L, column C: what
    is wrong (while ... from line L', column C')", lines and columns counted from 1."""
    mark, problem = getattr(err, "problem_mark", None), getattr(err, "problem", None)
    if mark is None or not problem:
        return " ".join(str(err).split())
    text = f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    context, cmark = getattr(err, "context", None), getattr(err, "context_mark", None)
    if context and cmark is not None:
        text += f" ({context} from line {cmark.line + 1}, column {cmark.column + 1})"
    return text
