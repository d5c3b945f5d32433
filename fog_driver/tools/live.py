"""``fog-driver watch``'s live state and its two outputs: on a terminal a block redrawn in place (at most
10 times a second, at least once a second), anywhere else one line per event and one compact line a second.

``LiveView.handle`` takes each protocol object; the rate shown is ``client.display.RateAverage``'s mean over the
last ``RATE_AVERAGE_S`` of device time (every frame's rate in it, the decimated ones too), as the web view's.
"""

from __future__ import annotations

import contextlib
from collections import deque
from collections.abc import Mapping
from typing import Any, TextIO

from ..client.display import RATE_AVERAGE_S, RateAverage, model_in_use, show
from ..client.wire import TOKEN_ENV
from .render import compact_line, device_text, identity_text, model_line, render, server_text
from .terminal import (
    CLEAR_EOL,
    CLEAR_EOS,
    CLEAR_SCREEN,
    HIDE_CURSOR,
    HOME,
    SHOW_CURSOR,
    degree_for,
    isatty,
    terminal_size,
)

__all__ = [
    "LINE_PERIOD_S",
    "RATE_AVERAGE_S",
    "RATE_WINDOW_S",
    "TTY_MIN_REDRAW_S",
    "TTY_REFRESH_S",
    "LiveView",
    "RateAverage",
]

TTY_MIN_REDRAW_S = 0.1  # at most 10 redraws a second
TTY_REFRESH_S = 1.0  # redraw at least this often (ages and rates move even without data)
LINE_PERIOD_S = 1.0  # non-tty: one compact line per second
RATE_WINDOW_S = 2.0  # ANGLE objects per second, counted over this window


class LiveView:
    """The client's state and its two views (terminal block, or log lines)."""

    def __init__(self, address: str, out: TextIO, started: float, *, keys: bool = False) -> None:
        self.out = out
        self.tty = isatty(out)
        self.degree = degree_for(out)
        self.started = started
        self.state: dict[str, Any] = {"address": address, "angles": 0, "malformed": 0, "unknown": 0, "keys": keys}
        self._arrivals: deque[float] = deque()
        self._rate = RateAverage()
        self._last_angle_at: float | None = None
        self._dirty = True
        self._last_draw: float | None = None
        self._drawn = False
        self._cursor_hidden = False
        self._next_line = started + LINE_PERIOD_S
        self._angles_at_last_line = 0
        self._lines_printed = 0
        self._model_shown: dict[str, Any] | None = None  #: the model a line named last (off a terminal)

    # -- input

    def handle(self, obj: dict[str, Any], now: float) -> None:
        cls = obj.get("class")
        if cls == "ANGLE":
            self.state["angle"] = obj
            self.state["angles"] += 1
            self._arrivals.append(now)
            self._last_angle_at = now
            self._rate.add(obj)
        elif cls == "STATUS":
            self.state["status"] = obj
            self._model_changed()
        elif cls == "VERSION":
            self.state["version"] = obj
            self._event(f"connected to {self.state['address']}: {server_text(obj)}; instrument {identity_text(obj)}")
            self._model_changed()
        elif cls == "DEVICE":
            self.state["device"] = obj
            down = "  *** LINK DOWN ***" if obj.get("state") == "deactivated" else ""
            self._event(f"device {device_text(obj)}{down}")
        elif cls == "WATCH":  # the server's answer to ?WATCH: the policy in force
            self.state["watch"] = obj
            self.state.pop("watch_refused", None)
        elif cls == "ERROR":
            message = show(obj.get("message")) if obj.get("message") is not None else "(no message)"
            if obj.get("command") == "WATCH":
                self.state["watch_refused"] = message
                hint = f" (set {TOKEN_ENV} or --token-file)" if message == "unauthorized" else ""
                self._event(f"?WATCH refused: {message}{hint}")
            elif obj.get("command") in ("ZERO", "BIAS"):
                hint = f" (set {TOKEN_ENV} or --token-file)" if message == "unauthorized" else ""
                self._action(f"?{obj['command']} refused: {message}{hint}")
            else:
                self.state["error"] = message
                self._event(f"server error: {message}")
        elif cls == "ZERO":
            self._rate.reset()
            self._action("zeroed: the angle starts again from 0 here")
        elif cls == "BIAS":
            self._bias(obj)
        elif cls == "AUTH":
            pass
        else:
            self.state["unknown"] += 1
        self._dirty = True

    def _model_changed(self) -> None:
        """Off a terminal, a line naming the model in use when it is first known and after each reload."""
        model_file = dict(model_in_use(self.state.get("status") or {}, self.state.get("version") or {}))
        if model_file and model_file != self._model_shown:
            self._model_shown = model_file
            self._event(f"model {model_line(model_file)}")

    def _bias(self, obj: Mapping[str, Any]) -> None:
        state = obj.get("state")
        if state == "started":
            self._action(f"bias capture started: {show(obj.get('seconds'), 'g')} s of data; keep the table still")
        elif state == "done":
            self._action(
                f"bias captured: {show(obj.get('bias_dph'), '.4f')} deg/h over "
                f"{show(obj.get('seconds'), '.1f')} s, removed from rate and angle from now on"
            )
        elif state == "failed":
            self._action(f"bias capture failed: {show(obj.get('reason'))}")

    def _action(self, text: str) -> None:
        self.state["action"] = text
        self._event(text)

    def idle_s(self, now: float) -> float:
        """Host seconds since the last ANGLE (since the watch started, before the first)."""
        return now - (self.started if self._last_angle_at is None else self._last_angle_at)

    def malformed(self, n: int = 1) -> None:
        self.state["malformed"] += n
        self._dirty = True

    # -- output

    def _snapshot(self, now: float) -> dict[str, Any]:
        while self._arrivals and self._arrivals[0] <= now - RATE_WINDOW_S:
            self._arrivals.popleft()
        window = min(RATE_WINDOW_S, now - self.started)
        self.state["elapsed_s"] = now - self.started
        self.state["angle_rate_hz"] = len(self._arrivals) / window if window > 0 else 0.0
        if self._last_angle_at is not None:
            self.state["angle_age_s"] = now - self._last_angle_at
        mean = self._rate.mean()
        self.state["rate_mean_dph"], self.state["rate_span_s"] = mean if mean is not None else (None, None)
        return self.state

    def _write(self, text: str) -> None:
        self.out.write(text)
        self.out.flush()

    def _event(self, line: str) -> None:
        if not self.tty:
            self._write(line + "\n")

    def _draw(self, now: float) -> None:
        columns, rows = terminal_size(self.out)
        width, height = max(20, columns), max(3, rows)
        lines = render(self._snapshot(now), width=width - 1, degree=self.degree, height=height - 1)[: height - 1]
        prefix = HIDE_CURSOR + HOME + CLEAR_SCREEN if not self._drawn else HOME
        body = "".join(line[: width - 1] + CLEAR_EOL + "\n" for line in lines)
        self._drawn = self._cursor_hidden = True
        self._write(prefix + body + CLEAR_EOS)
        self._last_draw = now
        self._dirty = False

    def redraw_all(self) -> None:
        """Clear and draw the whole block at the next tick (after the terminal was given back to the shell)."""
        self._drawn = False
        self._last_draw = None

    def _print_line(self, now: float) -> None:
        self._write(compact_line(self._snapshot(now), degree=self.degree) + "\n")
        self._angles_at_last_line = self.state["angles"]
        self._lines_printed += 1

    def tick(self, now: float) -> None:
        if self.tty:
            since = None if self._last_draw is None else now - self._last_draw
            if since is None or (self._dirty and since >= TTY_MIN_REDRAW_S) or since >= TTY_REFRESH_S:
                self._draw(now)
        elif now >= self._next_line:
            self._print_line(now)
            # keep the one-a-second cadence; after a stall, start again from now
            self._next_line = max(self._next_line + LINE_PERIOD_S, now)

    def finish(self, now: float, note: str | None = None) -> None:
        """The last view (so a short run shows what it got), then the note, if any."""
        if self.tty:
            self._draw(now)
            self.restore()
        elif self.state["angles"] > self._angles_at_last_line or (self._lines_printed == 0 and note is None):
            self._print_line(now)
        if note:
            self._write(note + "\n")

    def restore(self) -> None:
        """Show the cursor again (once), however the watch ends."""
        if self._cursor_hidden:
            self._cursor_hidden = False
            with contextlib.suppress(OSError, ValueError):
                self._write(SHOW_CURSOR)
