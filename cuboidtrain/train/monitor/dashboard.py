"""The trainer's dashboard: a rich panel when stdout is a terminal, log lines otherwise.

The trainer builds a `TrainerStatus` (cuboidtrain.train.monitor.status) about once a second,
hands it to `Dashboard.update` and writes it to OUT/status.json. Rendering is a
pure function of that status, so it can be tested as text and `watch` can show a
run from another terminal by re-reading the file. Any value may be None while it
is not known yet; it then shows as "—".
"""
from __future__ import annotations

import logging
import math
import statistics
import time
from dataclasses import replace
from pathlib import Path

from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.panel import Panel
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from cuboidtrain.train.monitor.status import FINISHED, BatchFreshness, Checkpoint, TrainerStatus, Validation, read_status, trainer_died
from shared.console import ECHO_ROOM, console as log_console

log = logging.getLogger(__name__)

DASH = "—"
SPARK = "▁▂▃▄▅▆▇█"
SPARK_POINTS = 30  # points of loss_history drawn as the trend
CHANGE_STEPS = 20  # the change column: the mean of this many last steps against the as many before
WAIT_TARGET = 0.05  # data-wait fraction of step time above which the loader is starving the GPU
WAIT_WARNING = 0.20  # and above which the GPU mostly idles: a warning (issue 29)
# Short words for the title line; config.PHASES has the full sentences.
PHASE_MEANING = {"1": "separate networks", "2": "chained", "e2e": "ablation: end to end",
                 "finetune": "ablation: fine-tune"}
LOSSES = (("D_R", "Refiner"), ("D_S", "Estimator"), ("D_T", "Tabulator"), ("total", "weighted sum"))
STATE_STYLE = {"training": "green", "waiting for samples": "yellow", "stopping after this step": "bold yellow",
               "checkpointing": "cyan",
               "evaluating": "cyan", "done": "bold green", "stopped": "bold yellow",
               "gave up": "bold red", "failed": "bold red"}


# --- formatting: every helper takes None and gives "—" -----------------------------------

def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def fmt_duration(seconds: float | None) -> str:
    """42s, 3m05s, 1h02m."""
    if not _finite(seconds):
        return DASH
    s = max(0, round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def fmt_loss(x: float | None) -> str:
    """Four figures that stay readable as a loss falls: 4.650, 0.0500, 1.23e-05; NaN shows as nan."""
    if x is None:
        return DASH
    if x != 0 and abs(x) < 1e-3:
        return f"{x:.2e}"
    return f"{x:.4f}" if abs(x) < 1 else f"{x:.3f}"


def _num(x, spec: str, suffix: str = "") -> str:
    return DASH if x is None else f"{x:{spec}}{suffix}"


def _of(done, total) -> str:
    return _num(done, ",") + (f" / {total:,}" if total is not None else "")


def sparkline(values: list[float] | None, points: int = SPARK_POINTS) -> str:
    """The last `points` finite values as block characters, scaled to their own range."""
    ys = [v for v in (values or [])[-points:] if _finite(v)]
    if not ys:
        return DASH
    lo, hi = min(ys), max(ys)
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):  # flat: a mid line, not a row of minimum blocks
        return SPARK[3] * len(ys)
    return "".join(SPARK[round((y - lo) / (hi - lo) * (len(SPARK) - 1))] for y in ys)


def trend(values: list[float] | None, steps: int = CHANGE_STEPS) -> Text:
    """The mean of the last `steps` steps' losses against the mean of the `steps` before them; a
    falling loss is green. Means, not the first point against the last: one step's loss is noisy
    (a D_T of 0.001 at the first point read "up 4031%" at the stop), and the history is this run's
    own, so the first steps after `--init` or a resume are never the yardstick of a later phase.
    A dash until the run has taken two windows of steps."""
    ys = [v for v in (values or []) if _finite(v)]
    if len(ys) < 2 * steps:
        return Text(DASH)
    before, last = statistics.fmean(ys[-2 * steps:-steps]), statistics.fmean(ys[-steps:])
    if before == 0:
        return Text(DASH)
    pct = (last - before) / abs(before) * 100
    if abs(pct) < 1:
        return Text(f"→ {pct:+.0f}%", style="dim")
    return Text(f"↓ {-pct:.0f}%", style="green") if pct < 0 else Text(f"↑ {pct:.0f}%", style="red")


def wait_cell(fraction: float | None) -> Text:
    """Data wait as a share of step time: the target is under 5%; above it the GPU idles, and
    above 20% it mostly idles."""
    if fraction is None:
        return Text(DASH)
    if fraction > WAIT_WARNING:
        return Text(f"{fraction:.1%} > {WAIT_WARNING:.0%}: warning, the device idles waiting for the loader", style="bold red")
    if fraction > WAIT_TARGET:
        return Text(f"{fraction:.1%} > {WAIT_TARGET:.0%}: loader starving", style="bold red")
    return Text(f"{fraction:.1%}")


def _skipped(skipped: dict | None) -> str:
    if not skipped:
        return DASH
    counts = ", ".join(f"{reason.replace('_', ' ')} {n}" for reason, n in skipped.items())
    return f"{sum(n or 0 for n in skipped.values())} ({counts})"


# --- the panel ----------------------------------------------------------------------------

def _title(s: TrainerStatus) -> Text:
    phase, size, state = s.phase, s.size, s.state or DASH
    meaning = PHASE_MEANING.get(str(phase))
    text = Text(f"phase {phase or DASH}" + (f" ({meaning})" if meaning else ""), style="bold")
    sample = " ".join(part for part in (s.shape, f"{size}x{size} px" if size else None) if part)
    text.append(f" · {sample or DASH} · {s.device or DASH} · ")
    text.append(state, style=STATE_STYLE.get(state, ""))
    return text


def _progress(s: TrainerStatus) -> Table:
    step, total = s.step, s.steps_total
    grid = Table.grid(padding=(0, 2))
    row: list[RenderableType] = [f"step {_of(step, total)}"]
    if step is not None and total:  # a bar only when the end is known in steps
        row += [ProgressBar(total=total, completed=min(step, total), width=30), f"{step / total:.1%}"]
    row += [f"epoch {_of(s.epoch, s.epochs_total)}",
            f"batch {_of(s.batch_in_epoch, s.batches_in_epoch)}",
            f"ETA {fmt_duration(s.eta_s)}"]
    grid.add_row(*row)
    return grid


def _losses(s: TrainerStatus) -> Table:
    losses, history, weights = s.losses, s.loss_history, s.loss_weights
    table = Table("loss", "", "value", "weight", f"trend (last {SPARK_POINTS})",
                  f"change (last {CHANGE_STEPS} steps vs {CHANGE_STEPS} before)", box=None)
    for i, (name, network) in enumerate(LOSSES):
        weight = _num(weights[i] if i < len(weights) else None, "g")
        weight = "" if name == "total" else weight  # the total is the weighted sum itself
        table.add_row(name, Text(network, style="dim"), fmt_loss(losses.get(name)), weight,
                      sparkline(history.get(name)), trend(history.get(name)), style="bold" if name == "total" else "")
    return table


def _checkpoint(ckpt: Checkpoint | None, now: float) -> str:
    if not ckpt:
        return DASH
    age = f", {fmt_duration(now - ckpt.time)} ago" if ckpt.time is not None else ""
    return f"step {_num(ckpt.step, ',')}{age}"


def _validation(val: Validation | None) -> str:
    if not val:
        return DASH
    return (f"mean {_num(val.mean_px_error, '.2f', ' px')}, median "
            f"{_num(val.median_px_error, '.2f', ' px')} (step {_num(val.step, ',')})")


def _facts(s: TrainerStatus, now: float) -> Table:
    fresh, skipped = s.freshness or BatchFreshness(), s.skipped
    updated = fmt_duration(now - s.updated) if s.updated is not None else DASH
    grid = Table.grid(padding=(0, 2))
    grid.add_row("throughput", f"{_num(s.samples_per_s, ',.1f')} samples/s, "
                 f"{_num(s.step_time_s, '.2f', ' s')}/step",
                 "data wait", wait_cell(s.data_wait_fraction))
    grid.add_row("spool", f"{s.spool or DASH}: {_num(s.spool_samples, ',')} samples, "
                 f"{_num(s.spool_arrivals_per_s, ',.0f')} arriving/s",
                 "freshness", f"mean age {fmt_duration(fresh.mean_age_s)}, "
                 f"mean reuse {_num(fresh.mean_reuse, '.1f')}")
    grid.add_row("skipped", Text(_skipped(skipped), style="yellow" if any(skipped.values()) else ""),
                 "checkpoint", _checkpoint(s.last_checkpoint, now))
    grid.add_row("validation", _validation(s.val),
                 "run", f"{s.out or DASH}, pid {_num(s.pid, 'd')}, updated {updated} ago")
    return grid


def render(status: TrainerStatus, now: float | None = None, width: int | None = None) -> Panel:
    """The dashboard for one status; `now` (unix s) dates the checkpoint and the update;
    `width` in columns (None: the console's)."""
    now = time.time() if now is None else now
    parts: list[RenderableType] = [_title(status), _progress(status), _losses(status), _facts(status, now)]
    parts += [Text(note, style="yellow") for note in status.notes]
    return Panel(Group(*parts), title="cuboidtrain", title_align="left", width=width)


def log_line(status: TrainerStatus) -> str:
    """The main figures as one plain line, for log files and non-terminals."""
    s, fresh, ckpt = status, status.freshness or BatchFreshness(), status.last_checkpoint or Checkpoint()
    total = f"/{s.steps_total}" if s.steps_total else ""
    progress = f"step {_num(s.step, 'd')}{total} epoch {_num(s.epoch, 'd')}"
    if s.eta_s is not None:
        progress += f" eta {fmt_duration(s.eta_s)}"
    parts = [progress,
             " ".join(f"{name} {fmt_loss(s.losses.get(name))}" for name, _ in LOSSES),
             f"{_num(s.samples_per_s, '.1f')} samples/s wait {_num(s.data_wait_fraction, '.1%')}",
             f"age {fmt_duration(fresh.mean_age_s)} reuse {_num(fresh.mean_reuse, '.1f')}",
             f"skipped {sum(n or 0 for n in s.skipped.values())}",
             f"ckpt step {_num(ckpt.step, 'd')}"]
    if s.val:
        parts.append(f"val {_num(s.val.mean_px_error, '.2f')} px")
    if s.state not in (None, "training"):  # the usual state goes without saying
        parts.insert(0, str(s.state))
    return " | ".join(parts + list(s.notes))


class Dashboard:
    """A live panel redrawn on each update, or else a log line at most every `log_interval`
    seconds and on every change of state.

    The panel is drawn on the console every log line goes through (stderr: `shared.console`), so
    that a warning logged while it is live (samples evicted unread, at an epoch's change) is printed
    above it: a line written past rich's Live, on another console, is not erased by its next redraw,
    which then leaves the top of the last panel behind, a stale frame a warning."""

    def __init__(self, live: bool, console: Console | None = None, log_interval: float = 10.0):
        self.console = console or log_console
        self.log_interval = log_interval
        # No auto refresh: the trainer updates about once a second, and a redraw between
        # updates would show nothing new.
        self._live = Live(console=self.console, auto_refresh=False, transient=False) if live else None
        self._started = False
        self._last_log: float | None = None  # nothing logged yet: the first update logs
        self._last_state: str | None = None
        self._unlogged: TrainerStatus | None = None  # the newest status not yet logged: close() logs it

    def __enter__(self) -> "Dashboard":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, status: TrainerStatus) -> None:
        if self._live is not None:
            if not self._started:  # started on first use so the panel never shows empty
                self._live.start()
                self._started = True
            # Narrower than the terminal: an echoed "^C" must not wrap (shared.console.ECHO_ROOM).
            self._live.update(render(status, width=max(self.console.width - ECHO_ROOM, 40)), refresh=True)
            return
        state = status.state
        if (self._last_log is None or state != self._last_state
                or time.monotonic() - self._last_log >= self.log_interval):
            self._last_log, self._last_state, self._unlogged = time.monotonic(), state, None
            log.info("%s", log_line(status))
        else:
            self._unlogged = status

    def close(self) -> None:
        """Stop the live panel (it stays on screen), or log the last figures if they were not."""
        if self._started:
            self._live.stop()
            self._started = False
        if self._unlogged is not None:
            log.info("%s", log_line(self._unlogged))
            self._unlogged = None


# --- watch: the dashboard of a run, from its status.json --------------------------------

def _annotated(status: TrainerStatus) -> TrainerStatus:
    if not trainer_died(status):
        return status
    note = f"trainer (pid {status.pid}) is not running; showing its last status"
    return replace(status, notes=[note, *status.notes])


def watch(out: Path, interval: float = 1.0, once: bool = False, console: Console | None = None) -> int:
    """Show the dashboard of the run in `out` until it is done or stopped, its trainer dies,
    or Ctrl-C. Returns 1 when the trainer died before finishing, gave up or failed, else 0."""
    console = console or Console()
    status = read_status(out)
    if once:
        console.print(render(_annotated(status)))
        return _exit_code(status)
    try:
        with Live(render(_annotated(status)), console=console, auto_refresh=False, transient=False) as live:
            while status.state not in FINISHED and not trainer_died(status):
                time.sleep(interval)
                try:
                    status = read_status(out)
                except ValueError:  # moved away or garbled for a moment: keep showing the last one
                    pass
                live.update(render(_annotated(status)), refresh=True)
    except KeyboardInterrupt:
        return 0
    return _exit_code(status)


def _exit_code(status: TrainerStatus) -> int:
    """1 when the trainer died before finishing, gave up waiting for samples or failed, else 0."""
    return int(trainer_died(status) or status.state in ("gave up", "failed"))
