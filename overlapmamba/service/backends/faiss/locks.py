"""A readers-writer lock for a map: searches share it, writes take it alone."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator


class RWLock:
    """Many readers or one writer, phase-fair: a waiting writer keeps new readers out (writes
    are never starved by a stream of searches), and the readers that queued behind a write
    go in together before the next write (a snapshot, a rebuild or a search is never held
    off by writers that follow one another, each waiting while another writes)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._readers = 0
        self._writer = False
        self._waiting_writers = 0
        self._queued_readers = 0  # readers waiting for a write phase to end
        self._entitled = 0  # of those, the ones a finished write let in before the next
        self._phase = 0  # writes finished

    @contextlib.contextmanager
    def read(self) -> Iterator[None]:
        with self._cond:
            if self._writer or self._waiting_writers:
                self._queued_readers += 1
                phase = self._phase
                try:
                    while self._writer or (self._waiting_writers and self._phase == phase):
                        self._cond.wait()
                finally:  # a wait cut short (an exception in this thread) gives its place up
                    self._queued_readers -= 1
                    if self._phase != phase:
                        self._entitled -= 1
                        self._cond.notify_all()
            self._readers += 1
        try:
            yield
        finally:
            with self._cond:
                self._readers -= 1
                if not self._readers:
                    self._cond.notify_all()

    @contextlib.contextmanager
    def write(self) -> Iterator[None]:
        with self._cond:
            self._waiting_writers += 1
            try:
                while self._writer or self._readers or self._entitled:
                    self._cond.wait()
            finally:  # acquired, or a wait cut short: either way it waits no more
                self._waiting_writers -= 1
                self._cond.notify_all()
            self._writer = True
        try:
            yield
        finally:
            with self._cond:
                self._writer = False
                self._phase += 1
                self._entitled = self._queued_readers  # they go in before the next write
                self._cond.notify_all()
