"""The streamer's primitive worker: parses and prepares primitive messages off the executor
and tick threads (the latest message wins), so a large primitive never delays a tick."""
import threading
from typing import Optional, Tuple

from cdmp_ros.core.errors import CdmpError


class PrimitiveWorker(threading.Thread):
    """Prepares the latest primitive message off the executor thread."""

    def __init__(self, prepare):
        super().__init__(name='primitive-worker', daemon=True)
        self._prepare = prepare
        self._cv = threading.Condition()
        self._pending: Optional[Tuple[str, str]] = None
        self._results = []
        self._stopping = False

    def submit(self, topic: str, text: str) -> Optional[str]:
        """Queue ``text``; returns the topic of a waiting message it replaced (never parsed),
        or None."""
        with self._cv:
            replaced = self._pending[0] if self._pending is not None else None
            self._pending = (topic, text)  # coalesce: only the newest counts
            self._cv.notify()
        return replaced

    def take(self):
        """Results since the last call: list of (topic, prepared or None, error or None)."""
        if not self._results:
            return ()
        with self._cv:
            out, self._results = self._results, []
        return out

    def stop(self) -> None:
        with self._cv:
            self._stopping = True
            self._cv.notify()

    def run(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                topic, text = self._pending
                self._pending = None
            try:
                res = (topic, self._prepare(topic, text), None)
            except CdmpError as exc:
                res = (topic, None, str(exc))
            except Exception as exc:  # noqa: BLE001 -- a worker must survive any payload
                res = (topic, None, f'{topic}: cannot be prepared: {exc!r}')
            with self._cv:
                self._results.append(res)
