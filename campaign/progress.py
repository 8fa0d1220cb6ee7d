"""A small progress bar on stderr: counts, rate and ETA. Silent unless enabled."""

from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, label: str, total: int | None = None, enabled: bool = False, unit: str = ""):
        self.label, self.total, self.enabled, self.unit = label, total, enabled, unit
        self.done = 0
        self.t0 = time.perf_counter()
        self._last = 0.0
        self.extra = ""
        self.eta_s = None  # the caller's own estimate of the time left (s), else done / rate

    def update(self, n: int = 1, extra: str = "", eta_s: float | None = None) -> None:
        self.done += n
        if extra:
            self.extra = extra
        if eta_s is not None:
            self.eta_s = eta_s
        now = time.perf_counter()
        if self.enabled and (now - self._last > 0.2 or (self.total and self.done >= self.total)):
            self._last = now
            self._draw(now)

    def _draw(self, now):
        el = now - self.t0
        rate = self.done / el if el > 0 else 0.0
        if self.total:
            frac = min(self.done / self.total, 1.0)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            eta = self.eta_s if self.eta_s is not None else (self.total - self.done) / rate if rate > 0 else float("inf")
            eta = f"ETA {eta:4.0f} s" if eta < float("inf") else "ETA    ? s"
            text = f"\r{self.label:<22} [{bar}] {self.done:,}/{self.total:,}{self.unit} {rate:,.0f}/s {eta} {self.extra}"
        else:
            text = f"\r{self.label:<22} {self.done:,}{self.unit} {rate:,.0f}/s {self.extra}"
        sys.stderr.write(text[:160])
        sys.stderr.flush()

    def close(self, message: str = "") -> None:
        if self.enabled:
            self._draw(time.perf_counter())
            el = time.perf_counter() - self.t0
            sys.stderr.write(f"  {el:.1f} s {message}\n")
            sys.stderr.flush()
