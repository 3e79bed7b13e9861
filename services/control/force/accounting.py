"""`StreamAccounting`: what the streaming sensor backends (`SerialSensor`, `NetFTSensor`)
share: sample-number gaps and bad-data counts, each reported as an event.
"""

from __future__ import annotations

from typing import Any

from services.control.force.events import EventSink


class StreamAccounting:
    """What a streaming device backend counts: its sample numbers (modulo `seq_modulo`,
    gaps reported as `gap` events) and the bad data it refused (`bad_data` events).

    A subclass sets `seq_modulo` and `unit` (what one sample is called in a message),
    calls `_init_accounting()` from its constructor and has `name` and `on_event`.
    """

    seq_modulo: int
    unit: str
    on_event: EventSink

    def _init_accounting(self) -> None:
        self._last_seq: int | None = None
        self._bad = 0
        self._gaps = 0

    @property
    def name(self) -> str:
        raise NotImplementedError

    @property
    def bad(self) -> int:
        return self._bad

    @property
    def gaps(self) -> int:
        return self._gaps

    def _step(self, seq: int, refuse_late: bool = False) -> int:
        """Take sample number `seq`: 0 to refuse it (a repeat, or with `refuse_late` one
        from behind: more than half the modulo back), else its step from the last one
        taken (1 when none is missing)."""
        last = self._last_seq
        if last is None:
            self._last_seq = seq
            return 1
        step = (seq - last) % self.seq_modulo
        if step == 0 or (refuse_late and step > self.seq_modulo // 2):
            return 0
        self._last_seq = seq
        if step > 1:
            self._gaps += step - 1
            self.on_event(
                "gap",
                f"{self.name}: {step - 1} {self.unit} missing before {seq}",
                {"missing": step - 1, "gaps": self._gaps},
            )
        return step

    def _bad_data(self, message: str, reason: str, **extra: Any) -> None:
        self._bad += 1
        self.on_event(
            "bad_data", f"{self.name}: {message}", {"reason": reason, "bad": self._bad, **extra}
        )
