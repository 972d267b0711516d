"""The dashboard renders its figures as text, and the log line carries the same ones."""
from rich.console import Console

from cuboidgen.dashboard import GenSnapshot, WorkerView, human_age, human_bytes, log_line, render


def snapshot(**changes) -> GenSnapshot:
    values = dict(
        elapsed=75.0,
        workers=[WorkerView(1200, 200, 0, 950.0, "running"), WorkerView(1100, 180, 2, 900.0, "disk full, backing off")],
        spool="data_spool", spool_samples=10_000, spool_bytes=170_000_000, limit=10_000, max_samples=None,
        oldest_age=11.0, newest_age=0.2, notes=["disk full: workers back off and resume when space returns"],
    )
    values.update(changes)
    return GenSnapshot(**values)


def as_text(renderable) -> str:
    console = Console(record=True, width=110, color_system=None)
    console.print(renderable)
    return console.export_text()


def test_dashboard_shows_rates_spool_and_workers():
    text = as_text(render(snapshot()))
    for expected in ("1,850", "950", "900", "10,000 / 10,000", "162.1 MiB", "2,300", "380",
                     "disk full, backing off", "11.0 s", "0.2 s", "75.0 s"):
        assert expected in text, expected


def test_retained_spool_says_so():
    assert "retained (no limit)" in as_text(render(snapshot(limit=0, max_samples=500)))


def test_log_line_has_the_same_figures():
    line = log_line(snapshot(max_samples=5000))
    assert "1,850 samples/s" in line and "published 2,300/5,000" in line and "evicted 380" in line
    assert "errors 2" in line and "disk full" in line


def test_human_units():
    assert human_bytes(512) == "512 B" and human_bytes(17 * 1024) == "17.0 KiB"
    assert human_bytes(170_000_000) == "162.1 MiB" and human_bytes(3 * 1024**3) == "3.0 GiB"  # binary units
    assert human_age(None) == "-" and human_age(5400) == "90.0 min" and human_age(9000) == "2.5 h"


def test_log_mode_is_due_only_every_log_interval():
    from cuboidgen.dashboard import Dashboard

    board = Dashboard(live=False, log_every=3600.0, console=Console(file=open("/dev/null", "w")))
    assert board.due()  # nothing logged yet
    board.update(snapshot())
    assert not board.due() and board.due(final=True)


def test_the_log_line_names_workers_that_are_not_running():
    assert "| workers" not in log_line(snapshot(workers=[WorkerView(5, 0, 0, 1.0, "running")], notes=[]))
    line = log_line(snapshot(workers=[WorkerView(5, 0, 0, 0.0, "done"), WorkerView(4, 0, 0, 0.0, "done")], notes=[]))
    assert line.endswith(" | workers 2 done")


def test_the_live_panel_leaves_room_for_the_echoed_ctrl_c():
    # A full-width last line would make the terminal wrap the echoed "^C" onto a new line,
    # and the next redraw would then start a line too low: the top border twice.
    import io
    import re

    from cuboidgen.dashboard import ECHO_ROOM, Dashboard

    out = io.StringIO()
    console = Console(file=out, force_terminal=True, width=80, color_system=None)
    with Dashboard(live=True, console=console) as board:
        board.update(snapshot(), final=True)
    lines = [re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", line) for line in out.getvalue().splitlines()]
    drawn = [line for line in lines if line.strip()]
    assert drawn[0].startswith("╭") and max(len(line) for line in drawn) == 80 - ECHO_ROOM
