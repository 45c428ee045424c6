"""Background jobs for the modal operators (pure Python, no bpy).

A :class:`Job` wraps a callable that does the long work (``tyndall.render``, ``tyndall.sky``,
file writes into a staging folder) and never touches bpy. The modal operator starts it,
polls it from a timer on Blender's main thread and, when it is done, commits the result
there. With EXEC_DEFAULT the operator calls :meth:`Job.run` instead, which runs the same
work to completion in the calling thread.

States::

    PENDING --start()/run()--> RUNNING --work returns--> DONE
                                  |     --work raises--> FAILED
                                  +--cancel()----------> CANCELLED

Cancelling sets :attr:`Job.stop_requested`, which the work passes to ``tyndall.render`` /
``render_to_files`` / ``tyndall.sky`` as ``cancel=``: the Rust renderer then stops within
about one view ray's time (the sky within one round of its grid or one row) and raises
``tyndall.RenderCancelled``. Work that cannot be stopped runs on. Either way its result is
discarded when the worker returns (``on_discard`` runs in the worker, e.g. to delete the
staging folder); the caller stops waiting immediately.
"""

from __future__ import annotations

import enum
import threading
import time
from collections.abc import Callable
from typing import Any


class JobState(enum.Enum):
    """Where a job is in its life cycle."""

    PENDING = "pending"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def finished(self) -> bool:
        """True in the three final states."""
        return self in (JobState.DONE, JobState.FAILED, JobState.CANCELLED)


ProgressFn = Callable[[float, str], None]
WorkFn = Callable[[ProgressFn], Any]


class JobStateError(RuntimeError):
    """An operation that the job's current state does not allow (start twice, result before done…)."""


class Job:
    """One unit of background work with progress, cancellation and a result.

    ``work(progress)`` is called with a function ``progress(fraction, message)`` it may
    call from its thread. ``on_discard(result_or_None)`` is called (in the worker) when
    the job finishes after it was cancelled, or when the work failed.
    """

    def __init__(self, work: WorkFn, name: str = "job", on_discard: Callable[[Any], None] | None = None) -> None:
        self.name = name
        self._work = work
        self._on_discard = on_discard
        self._lock = threading.Lock()
        self._state = JobState.PENDING
        self._result: Any = None
        self._error: BaseException | None = None
        self._progress = 0.0
        self._message = ""
        self._thread: threading.Thread | None = None
        self._started_at: float | None = None
        self._finished_at: float | None = None
        self._worker_done = threading.Event()
        #: Set by :meth:`cancel`; the work hands it to ``tyndall.render(..., cancel=)``.
        self.stop_requested = threading.Event()

    # -- state ----------------------------------------------------------------
    @property
    def state(self) -> JobState:
        with self._lock:
            return self._state

    def poll(self) -> JobState:
        """The current state, without blocking (what the modal timer calls)."""
        return self.state

    @property
    def progress(self) -> float:
        """Fraction 0..1 reported by the work (1 when done)."""
        with self._lock:
            return self._progress

    @property
    def message(self) -> str:
        with self._lock:
            return self._message

    @property
    def elapsed(self) -> float:
        """Seconds since start (until the end when finished)."""
        with self._lock:
            if self._started_at is None:
                return 0.0
            end = self._finished_at if self._finished_at is not None else time.monotonic()
            return end - self._started_at

    @property
    def error(self) -> BaseException | None:
        with self._lock:
            return self._error

    def result(self) -> Any:
        """The work's return value; only in state DONE."""
        with self._lock:
            if self._state is not JobState.DONE:
                raise JobStateError(f"{self.name}: no result in state {self._state.value}")
            return self._result

    # -- transitions ----------------------------------------------------------
    def _set_progress(self, fraction: float, message: str = "") -> None:
        with self._lock:
            if self._state is JobState.RUNNING:
                self._progress = min(max(float(fraction), 0.0), 1.0)
                if message:
                    self._message = message

    def _begin(self) -> None:
        with self._lock:
            if self._state is not JobState.PENDING:
                raise JobStateError(f"{self.name}: cannot start in state {self._state.value}")
            self._state = JobState.RUNNING
            self._started_at = time.monotonic()

    def _execute(self) -> None:
        result: Any = None
        error: BaseException | None = None
        try:
            result = self._work(self._set_progress)
        except BaseException as e:  # noqa: BLE001 - reported to the user via the operator
            error = e
        discard = False
        with self._lock:
            self._finished_at = time.monotonic()
            if self._state is JobState.CANCELLED:
                discard = True
            elif error is not None:
                self._state = JobState.FAILED
                self._error = error
                discard = True
            else:
                self._state = JobState.DONE
                self._result = result
                self._progress = 1.0
        if discard and self._on_discard is not None:
            try:
                self._on_discard(result)
            except Exception:  # noqa: BLE001 - cleanup must not mask the outcome
                pass
        self._worker_done.set()

    def start(self) -> None:
        """Run the work in a daemon thread (INVOKE_DEFAULT)."""
        self._begin()
        self._thread = threading.Thread(target=self._execute, name=f"tyndall-{self.name}", daemon=True)
        self._thread.start()

    def run(self) -> JobState:
        """Run the work to completion in the calling thread (EXEC_DEFAULT); returns the final state."""
        self._begin()
        self._execute()
        return self.state

    def cancel(self) -> bool:
        """Stop waiting: RUNNING/PENDING → CANCELLED, and ask the work to stop (:attr:`stop_requested`).

        The result is discarded when the worker ends.

        Returns False if the job had already finished.
        """
        with self._lock:
            if self._state.finished:
                return False
            was_pending = self._state is JobState.PENDING
            self._state = JobState.CANCELLED
            if self._finished_at is None:
                self._finished_at = time.monotonic()
        self.stop_requested.set()
        if was_pending:
            self._worker_done.set()
        return True

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the worker has returned (even after cancel); True if it did within ``timeout``."""
        return self._worker_done.wait(timeout)
