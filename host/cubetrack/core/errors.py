"""The one exception tree of cubetrack.

Every error a user can cause (a bad file, a bad option, a broken camera) is a subclass of
:class:`CubetrackError`; the command-line boundary prints its message on one line and exits 1.
Messages name the offending file or value and say what valid input looks like.
"""


class CubetrackError(Exception):
    """Base of every error cubetrack raises on bad input or a failing peer."""


class ConfigError(CubetrackError):
    """A tracker config, cube layout, extrinsics or parameter table is invalid."""


class ParamsError(ConfigError, ValueError):
    """A parameter value is out of range: the one error every params dataclass raises in its
    ``__post_init__``. The config loader (:func:`cubetrack.core.params.params_from_table`) turns
    it into a one-line :class:`ConfigError` naming the file and section."""


class CameraInfoError(CubetrackError):
    """An intrinsics file (ROS camera_info YAML or OpenCV FileStorage YAML) is missing or invalid."""


class RecordingError(CubetrackError):
    """A recording folder is missing or does not follow the recording contract."""


class TrajectoryError(CubetrackError):
    """A TUM or JSONL trajectory file is missing or malformed."""


class ImageError(CubetrackError):
    """An image cannot be read or decoded."""


class DetectionError(CubetrackError):
    """Detection was asked for something it cannot do (e.g. an unknown dictionary)."""


class EstimationError(CubetrackError):
    """Pose estimation got inconsistent inputs."""


class CalibrationError(CubetrackError):
    """Camera calibration could not produce a result (e.g. no world-marker sightings)."""


class SimulationError(CubetrackError):
    """A simulation scenario is impossible (e.g. a camera that sees nothing)."""


class EvaluationError(CubetrackError):
    """Evaluation inputs do not overlap or are empty."""


class SourceError(CubetrackError):
    """A camera source could not be started or read (e.g. the camera emulator failed)."""


def caused_by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` was caused, at any depth, by a KeyboardInterrupt: Ctrl-C (or SIGTERM/SIGHUP,
    which the CLI turns into it) while numba's C dispatcher loads a kernel from its cache comes out as
    a SystemError caused by the interrupt, which is an interrupt all the same. The chain is followed
    as a traceback shows it (``raise ... from None`` ends it)."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            return True
        seen = seen.__cause__ if seen.__cause__ is not None or seen.__suppress_context__ else seen.__context__
    return False


NO_NUMBA_CACHE_FOLDER = ("numba's cache needs a writable folder: NUMBA_CACHE_DIR, __pycache__ beside the sources or "
                         "~/.cache/numba")


def no_numba_cache_folder(exc: BaseException) -> bool:
    """Whether ``exc`` is numba refusing to define a cached kernel because it found no writable
    folder for its cache (a read-only install without ``NUMBA_CACHE_DIR`` or a writable home): the
    install's fault, not a bug (:data:`NO_NUMBA_CACHE_FOLDER` says what to do)."""
    return isinstance(exc, RuntimeError) and "no locator available" in str(exc)
