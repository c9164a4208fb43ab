"""SIGINT and SIGTERM for the ``vi3`` commands: a signal at any moment ends the program with status 128 + its number
(130 SIGINT, 143 SIGTERM), never by the signal's default action and never with a traceback; a command that writes an
output traps them so that it ends keeping a complete output, a partial one named as such, or nothing.

- ``exit_on_signal()``, the program's first step, makes SIGINT and SIGTERM end the process at once (saying so on
  stderr) while no command traps them: before a command starts (nothing was written) and after it finished (its
  outputs are final and reported), exit functions included. ``end(status)`` ends the program after its exit
  functions, skipping the interpreter's teardown of modules, where Python restores the signals' default actions.
- Inside ``trapped()`` (around every command; nested inside it by a command that writes an output), the first
  signal raises KeyboardInterrupt in the main thread, so that the command unwinds and keeps or removes what it
  wrote; later signals are only recorded, so that this cleanup is never cut short.
- Between ``hold()`` and ``release()`` (an output being created or moved into place, a decision about what is kept)
  and inside ``held()`` a signal is only recorded; ``release()`` raises it. The command reads ``Trap.signum`` to
  report it afterwards.

Outside ``trapped()`` (library use, tests) ``hold``, ``release`` and ``held`` do nothing. ``vi3_node`` traps SIGINT
and SIGTERM the same way around its whole life, so that its shutdown is never cut short by a second signal.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import NoReturn


@dataclass
class Trap:
    """signum: the first signal received (None: none yet); held: signals are only recorded; raised: the
    KeyboardInterrupt of the first signal has been raised; signums: the signals trapped."""

    signum: int | None = None
    held: bool = False
    raised: bool = False
    signums: tuple[int, ...] = ()

    @property
    def name(self) -> str:
        """The received signal's name; SIGINT for a KeyboardInterrupt that came without a trapped signal."""
        return signal.Signals(self.signum or signal.SIGINT).name

    @property
    def status(self) -> int:
        """The program's exit status for the received signal (128 + its number; SIGINT's, 130, when none was)."""
        return 128 + (self.signum or signal.SIGINT)


STARTING = "before the command started; nothing was written"
RUNNING = "while the command ran"
FINISHED = "after the command finished"
_trap: Trap | None = None
_phase = STARTING  # where the program is, for the message of ``exit_on_signal``'s handler
_status: int | None = None  # the program's exit status, once ``end`` has it


def _on_signal(signum: int, frame: object) -> None:
    trap = _trap
    if trap is None:  # no command running: nothing to unwind
        _exit_now(signum)
    if trap.signum is None:
        trap.signum = signum
    if not trap.held and not trap.raised:
        trap.raised = True
        raise KeyboardInterrupt


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, RuntimeError):  # closed, or interrupted in the middle of a write
            pass


def _exit_now(signum: int) -> None:
    _flush()
    os.write(2, f"vi3: interrupted by {signal.Signals(signum).name} {_phase}\n".encode())
    os._exit(128 + signum)


def _default_signums() -> tuple[int, ...]:
    """SIGTERM, and SIGINT unless it is ignored (as under nohup)."""
    return (signal.SIGTERM,) + ((signal.SIGINT,) if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN else ())


def exit_on_signal() -> None:
    """The program's first step: SIGINT or SIGTERM outside a command ends the process with status 128 + its number
    (see the module)."""
    for s in _default_signums():
        signal.signal(s, _on_signal)
    atexit.register(_end)  # the first exit function registered runs last


def end(status: int) -> NoReturn:
    """Exit with ``status``: the exit functions run (SIGTERM still ends the program with 143 meanwhile), then the
    process ends without the interpreter's teardown of modules (after ``exit_on_signal``)."""
    global _status
    _status = status
    sys.exit(status)


def _end() -> None:
    if _status is not None:  # not after an uncaught exception: the interpreter then exits its own way
        _flush()
        os._exit(_status)


def set_phase(phase: str) -> None:
    """Where the program is (STARTING, RUNNING or FINISHED), for the message of a SIGTERM outside ``trapped()``."""
    global _phase
    _phase = phase


@contextmanager
def trapped(signums: tuple[int, ...] | None = None) -> Iterator[Trap]:
    """``signums`` (default: SIGTERM, and SIGINT unless it is ignored, as under nohup) as described in the module,
    for the block; the previous handlers (and trap, when nested) after it. Off the main thread (Python lets only it
    set signal handlers) the trap is inert: no signal reaches it."""
    global _trap
    if threading.current_thread() is not threading.main_thread():
        yield Trap(held=True)
        return
    trap = Trap(signums=signums if signums is not None else _default_signums())
    previous = {s: signal.getsignal(s) for s in trap.signums}
    outer, _trap = _trap, trap
    reinstall()
    try:
        yield trap
    finally:
        trap.held = True  # the command is over: what it wrote is final
        if outer is None:
            set_phase(FINISHED)
        for s, handler in previous.items():
            signal.signal(s, handler)
        _trap = outer


def reinstall() -> None:
    """The current trap's handlers again, after a library replaced them (``ray.init`` sets its own SIGTERM
    handler, which exits with a traceback)."""
    if _trap is not None:
        for s in _trap.signums:
            signal.signal(s, _on_signal)


def hold() -> None:
    """From now on a signal is only recorded (see ``release``)."""
    if _trap is not None:
        _trap.held = True


@contextmanager
def held() -> Iterator[None]:
    """A block that a signal does not cut short (e.g. the messages of one clip written together): a signal that
    arrives meanwhile raises KeyboardInterrupt at its end. Nothing changes where signals are held already, outside
    ``trapped()`` or off the main thread (where no signal is raised)."""
    trap = _trap
    if trap is None or trap.held or threading.current_thread() is not threading.main_thread():
        yield
        return
    trap.held = True
    try:
        yield
    except BaseException:
        trap.held = False
        raise
    release()


def release() -> None:
    """Signals raise again; one that arrived since ``hold`` raises KeyboardInterrupt now."""
    trap = _trap
    if trap is None:
        return
    trap.held = False
    if trap.signum is not None and not trap.raised:
        trap.raised = True
        raise KeyboardInterrupt
