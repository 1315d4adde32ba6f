"""The streamer's primitive worker: parses and prepares primitive messages off the executor
and tick threads (the latest message of each topic wins), so a large primitive never delays a
tick. ``primitive`` and ``adapted_primitive`` wait in separate slots: a restarted streamer
receives both latched messages at once and needs both (issue 13, deterministic restart)."""
import threading
from typing import Dict, Optional

from cdmp_ros.core.errors import CdmpError


class PrimitiveWorker(threading.Thread):
    """Prepares the latest primitive message off the executor thread."""

    def __init__(self, prepare):
        super().__init__(name='primitive-worker', daemon=True)
        self._prepare = prepare
        self._cv = threading.Condition()
        self._pending: Dict[str, str] = {}  # topic -> newest unparsed text
        self._results = []
        self._stopping = False

    def submit(self, topic: str, text: str) -> Optional[str]:
        """Queue ``text``; returns ``topic`` if it replaced a waiting message of the same topic
        (never parsed), else None."""
        with self._cv:
            replaced = topic if topic in self._pending else None
            self._pending[topic] = text  # coalesce per topic: only the newest counts
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
                while not self._pending and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                topic = next(iter(self._pending))  # the oldest waiting topic first
                text = self._pending.pop(topic)
            try:
                res = (topic, self._prepare(topic, text), None)
            except CdmpError as exc:
                res = (topic, None, str(exc))
            except Exception as exc:  # noqa: BLE001 -- a worker must survive any payload
                res = (topic, None, f'{topic}: cannot be prepared: {exc!r}')
            with self._cv:
                self._results.append(res)
