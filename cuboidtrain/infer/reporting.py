"""What `cuboidtrain infer` tells a person: one line per record as each input completes (`Answer`),
how far the run is (a rich bar on a terminal, a log line every few seconds without one), and a total
at the end. The counting (`Tally`) and the answer's fields (`Answer.of`) are apart from the showing,
so tests read them.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

from rich.markup import escape


log = logging.getLogger(__name__)

LOG_SECONDS = 5.0  # between plain progress lines
WARNING_CHARS = 60  # the first warning is cut to this: a box's line then fits a 160-column terminal
INPUT_CHARS = 40  # an input's name longer than this keeps its end (the file's own name)
TRUST_STYLES = {"high": "green", "medium": "yellow", "low": "red"}


@dataclass(frozen=True)
class Ratio:
    """One ratio of an answer, per part: `values` are (part, value, sd) with part "" for a box and
    "R" / "L" for a twobox's right and left boxes; sd None without error bars."""

    name: str  # "d/h" or "w/h"
    values: tuple[tuple[str, float, float | None], ...]

    def text(self) -> str:
        def one(part: str, value: float, sd: float | None) -> str:
            return (f"{part} " if part else "") + f"{value:.2f}" + ("" if sd is None else f" ± {sd:.2f}")

        return f"{self.name} " + " / ".join(one(*v) for v in self.values)


@dataclass(frozen=True)
class Answer:
    """One infer record as a person reads it at a terminal, in one line (`cells`)."""

    input: str
    shape: str | None = None
    trust: tuple[str, float] | None = None  # the record's trust (level, score), where it has one
    confidence: float | None = None  # shown where the record has no trust
    ratios: tuple[Ratio, ...] = ()
    yaw: tuple[float, float | None] | None = None  # degrees and sd: the fitted cuboid's; None networks-only
    camera: str | None = None  # "camera given", "camera fitted", "focal given" ...; None: networks only
    warnings: tuple[str, ...] = ()
    error: str | None = None

    @classmethod
    def of(cls, record: dict) -> "Answer":
        """The answer of an infer record (docs/contract.md, "The infer record"), a fitted one or an error."""
        name = (record["input"] if record["input"] is not None else "mask")  # an array fitted through the API: no file
        name += f" #{record['component']}" if record.get("component") is not None else ""
        if record.get("error") is not None:
            return cls(name, error=record["error"])
        trust = record.get("trust")
        cuboid = record.get("cuboid")
        return cls(name, record["shape"], (trust["level"], float(trust["score"])) if trust else None,
                   record["confidence"], ratios_of(record["ratios"], record.get("ratios_sd")),
                   None if cuboid is None else (cuboid["yaw_deg"], cuboid.get("yaw_sd_deg")),
                   None if cuboid is None else camera_of(cuboid["intrinsics"]), tuple(record["warnings"]))

    def cells(self) -> list[tuple[str, str]]:
        """(text, rich style) per column: input, shape, trust, d/h, w/h, yaw, camera, warnings; an error's
        input and its reason."""
        name = self.input if len(self.input) <= INPUT_CHARS else "…" + self.input[-(INPUT_CHARS - 1):]
        if self.error is not None:
            return [(name, ""), (f"error: {self.error}", "red")]
        if self.trust is not None:
            trust = (f"trust {self.trust[0]} {self.trust[1]:.2f}", TRUST_STYLES.get(self.trust[0], ""))
        else:
            trust = (f"conf {self.confidence:.2f}", "")
        yaw = "" if self.yaw is None else f"yaw {self.yaw[0]:.0f}°" + (
            "" if self.yaw[1] is None else f" ± {self.yaw[1]:.0f}°")
        return [(name, ""), (self.shape, "bold"), trust, *((r.text(), "") for r in self.ratios),
                *([(yaw, "")] if yaw else []), (self.camera or "no cuboid fit", ""),
                (warnings_text(self.warnings), "yellow" if self.warnings else "")]

    def line(self, widths: Sequence[int] = ()) -> str:
        """The answer as plain text, each column padded to `widths` (the last never)."""
        cells = [text for text, _ in self.cells()]
        return "  ".join(pad(text, widths, k, len(cells)) for k, text in enumerate(cells))

    def markup(self, widths: Sequence[int] = ()) -> str:
        """`line` in rich markup: the trust level, warnings and errors coloured (a console without a
        terminal drops the colours)."""
        cells = self.cells()
        return "  ".join(f"[{style}]{escape(pad(text, widths, k, len(cells)))}[/]" if style else
                         escape(pad(text, widths, k, len(cells))) for k, (text, style) in enumerate(cells))


def pad(text: str, widths: Sequence[int], k: int, count: int) -> str:
    return text if k == count - 1 or k >= len(widths) else text.ljust(widths[k])


def ratios_of(ratios: dict, sds: dict | None) -> tuple[Ratio, ...]:
    """The record's ratios (a box's {"depth_height", "width_height"}, a twobox's per part) as Ratios."""
    parts = [("", ratios, sds)] if "depth_height" in ratios else \
        [(part[0].upper(), ratios[part], (sds or {}).get(part)) for part in ratios]
    return tuple(Ratio(label, tuple((p, values[key], None if sd is None else sd[key]) for p, values, sd in parts))
                 for label, key in (("d/h", "depth_height"), ("w/h", "width_height")))


SOURCE_WORDS = {"given": "given", "exif": "from EXIF", "fitted": "fitted"}  # the record's `intrinsics` values


def camera_of(intrinsics: dict) -> str:
    """Where the camera's focal length and principal point came from (the record's `intrinsics`:
    given, a photo's EXIF, or fitted), in words; the one known named first."""
    focal, principal = (SOURCE_WORDS[intrinsics[name]] for name in ("focal_px", "principal_px"))
    if focal == principal:
        return f"camera {focal}"
    if principal != "fitted" and focal == "fitted":
        return f"centre {principal}, focal {focal}"
    return f"focal {focal}, centre {principal}"


def warnings_text(warnings: Sequence[str]) -> str:
    """How many warnings and the first, cut at a word to WARNING_CHARS."""
    if not warnings:
        return "no warnings"
    first = warnings[0] if len(warnings[0]) <= WARNING_CHARS else \
        warnings[0][:WARNING_CHARS].rsplit(" ", 1)[0].rstrip(",;:") + "…"
    return f"{len(warnings)} warning{'' if len(warnings) == 1 else 's'}: {first}"


@dataclass
class Tally:
    """Inputs and their records counted as they complete (the records OUT already held apart)."""

    total: int  # inputs of the run, resumed ones included
    resumed: int = 0  # inputs OUT already held
    done: int = 0  # inputs tried this run, failed ones included
    failed: int = 0  # inputs whose first record has an error (this run and resumed)
    failed_now: int = 0  # of them, the inputs tried this run
    shapes: Counter = field(default_factory=Counter)  # records by shape class ("failed" for errors)
    trust: Counter = field(default_factory=Counter)  # fitted records by trust level, where records have one
    warned: int = 0  # fitted records with at least one warning
    stopped: str | None = None  # what stopped the run before its end ("Ctrl-C", "SIGTERM"), if anything
    started: float = field(default_factory=time.monotonic)

    def add(self, records: Sequence[dict]) -> None:
        """An input fitted this run: its records (an error's is a failed input)."""
        self.done += 1
        failed = bool(records) and records[0]["error"] is not None
        self.failed_now += failed
        self.count(records)

    def resume(self, records: Sequence[dict]) -> None:
        """An input OUT already held: its records, as read back."""
        self.resumed += 1
        self.count(records)

    def count(self, records: Sequence[dict]) -> None:
        self.failed += bool(records) and records[0]["error"] is not None
        self.shapes.update(r["shape"] or "failed" for r in records)
        fitted = [r for r in records if r["error"] is None]
        self.warned += sum(bool(r["warnings"]) for r in fitted)
        self.trust.update(r["trust"]["level"] for r in fitted if r.get("trust"))

    @property
    def fitted(self) -> int:
        """Inputs fitted this run: those tried, less those that failed (the summary's counts add up)."""
        return self.done - self.failed_now

    @property
    def rate(self) -> float:
        return self.done / max(time.monotonic() - self.started, 1e-9)

    def line(self) -> str:
        finished = self.resumed + self.done
        left = self.total - finished
        eta = f"ETA {left / self.rate:.0f} s" if self.rate > 0 else "ETA ?"
        return (f"{finished}/{self.total} masks, {self.rate:.1f} masks/s, {eta}, "
                f"{self.failed} failure{'' if self.failed == 1 else 's'}")

    def summary(self) -> str:
        seconds = time.monotonic() - self.started
        shapes = ", ".join(f"{name} {n}" for name, n in sorted(self.shapes.items()) if name != "failed") or "none"
        resumed = f" ({self.resumed} already in OUT)" if self.resumed else ""
        shown = self.total if self.stopped else self.resumed + self.done  # the number "masks" counts
        count = f"stopped by {self.stopped}: {self.resumed + self.done} of {self.total}" if self.stopped else \
            f"{self.resumed + self.done}"
        trust = "".join(f", {level} {self.trust[level]}" for level in TRUST_STYLES if self.trust[level])
        return (f"{count} mask{'' if shown == 1 else 's'}{resumed}; fitted {self.fitted} in {seconds:.1f} s "
                f"({self.rate:.1f} masks/s); records by shape: {shapes}; {self.failed} failed; "
                f"{self.warned} with warnings" + (f"; trust{trust[1:]}" if trust else ""))


def typical_answer(shape: str) -> Answer:
    """An answer of `shape` with cells as wide as most are (two-digit degrees, a medium trust)."""
    parts = ("R", "L") if shape == "twobox" else ("",)
    ratios = tuple(Ratio(name, tuple((part, 0.5, 0.1) for part in parts)) for name in ("d/h", "w/h"))
    return Answer("", shape, ("medium", 0.5), 0.5, ratios, (-10.0, 10.0), "camera fitted")


class Reporter:
    """Shows a Tally and each input's answers: `with Reporter(tally, console) as show: ...;
    show.add(records)` per input completed. The answers' columns are aligned: each is as wide as
    its widest cell so far (a name as long as the longest input's, up to INPUT_CHARS)."""

    def __init__(self, tally: Tally, console, inputs: Sequence[str] = (), shapes: Sequence[str] = ("box",)):
        self.tally, self.console = tally, console
        self.bar = None
        self.logged = time.monotonic()
        # the columns as wide as the run's inputs and a typical answer of its richest shape class need
        # (one input's line is not padded: there is nothing to align it with)
        self.widths = [len(text) for text, _ in typical_answer(max(shapes, key=len)).cells()[:-1]]
        self.widths[0] = min(max(map(len, inputs), default=0), INPUT_CHARS)
        self.align = len(inputs) > 1

    def __enter__(self) -> "Reporter":
        if self.console.is_terminal:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self.bar = Progress(TextColumn("fitting"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("{task.fields[rate]:.1f} masks/s"), TimeRemainingColumn(),
                                TimeElapsedColumn(), TextColumn("{task.fields[failed]} failed"),
                                console=self.console, transient=False)
            self.bar.start()
            self.task = self.bar.add_task("fit", total=self.tally.total, completed=self.tally.resumed,
                                          rate=0.0, failed=self.tally.failed)
        return self

    def add(self, records: Sequence[dict]) -> None:
        """An input fitted this run: its infer records (`records.to_records`, as OUT holds them) counted,
        a line each shown (above the bar)."""
        self.tally.add(records)
        for record in records:
            self.show(Answer.of(record))
        self.update()

    def show(self, answer: Answer) -> None:
        cells = answer.cells()
        for k, (text, _) in enumerate(cells[:-1]):
            if k == len(self.widths):
                self.widths.append(0)
            self.widths[k] = max(self.widths[k], len(text))
        self.console.print(answer.markup(self.widths if self.align else ()), highlight=False, soft_wrap=True)

    def update(self) -> None:
        tally = self.tally
        if self.bar is not None:
            self.bar.update(self.task, completed=tally.resumed + tally.done, rate=tally.rate, failed=tally.failed)
        elif time.monotonic() - self.logged >= LOG_SECONDS:
            self.logged = time.monotonic()
            log.info("%s", tally.line())

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.update()
            self.bar.stop()
        self.console.print(self.tally.summary(), highlight=False, soft_wrap=True)
