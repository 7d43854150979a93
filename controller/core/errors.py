"""Error types that the CLI turns into exit codes and messages (never tracebacks)."""
from __future__ import annotations


class ElastoprobeError(Exception):
    """Base of every error the product raises on purpose."""

    exit_code = 1


class InputError(ElastoprobeError):
    """Bad user input: a plan, a cell, an object file or a CLI argument.

    ``location`` is ``path:line:col`` when the error is in a file (1-based line
    and column), or a short name of the argument otherwise.
    """

    exit_code = 2

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None,
                 col: int | None = None) -> None:
        self.message = message
        self.path = path
        self.line = line
        self.col = col
        super().__init__(self.format())

    @property
    def location(self) -> str:
        if self.path is None:
            return ""
        if self.line is None:
            return f"{self.path}"
        return f"{self.path}:{self.line}:{self.col if self.col is not None else 1}"

    def format(self) -> str:
        loc = self.location
        return f"{loc}: {self.message}" if loc else self.message


class InputErrors(InputError):
    """Several input errors found in one validation pass (all reported at once)."""

    def __init__(self, errors: list[InputError]) -> None:
        if not errors:
            raise ValueError("InputErrors needs at least one error")
        self.errors = errors
        first = errors[0]
        super().__init__(first.message, path=first.path, line=first.line, col=first.col)

    def format(self) -> str:
        return "\n".join(e.format() for e in self.errors)


class DiskError(InputError):
    """A path cannot be written: a read-only disk, a full one, a file where a directory
    should be (exit 2 from a command; a pause inside a session, which resumes once the
    disk is fixed). The message names the path."""

    @classmethod
    def from_os_error(cls, exc: OSError, path: str, doing: str = "cannot write") -> "DiskError":
        why = exc.strerror or type(exc).__name__
        hint = {30: " (the disk is mounted read-only)", 28: " (the disk is full)",
                13: " (no permission)"}.get(exc.errno or 0, "")
        return cls(f"{doing}: {why}{hint}", path=path)


class DeviceError(ElastoprobeError):
    """A device misbehaved: lost connection, timeout, bad frame, refused command."""


class ProtocolError(DeviceError):
    """Bytes on a wire that do not follow the protocol (bad frame, checksum, size)."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its deadline."""


class ProgramNotRunning(DeviceError):
    """The robot's control program is not running (a safety stop, an operator's stop, the
    watchdog): a command could not be sent. The arm's status says why."""


class MotionRefused(ElastoprobeError):
    """A motion was rejected before being sent (IK, joint limits, workspace, collision)."""


class SafetyTrip(ElastoprobeError):
    """A safety limit was crossed; the arm has been stopped."""


class CalibrationError(ElastoprobeError):
    """A calibration was refused: degenerate or too few poses, or a poor fit (the reason says which)."""


class CalibrationFileError(CalibrationError):
    """A calibration file that cannot be used as it is (unreadable, damaged, another cell's):
    the user's file, so bad input (exit 2), not a fault of the cell."""

    exit_code = 2


class SessionAborted(Exception):
    """The fault policy said abort (exit 1)."""


class BudgetSpent(Exception):
    """The plan's step or robot-time budget is used up: the session wraps up what it has."""

