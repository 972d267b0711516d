"""What `cuboidtrain infer` tells a person (cuboidtrain/infer/reporting.py): a line per record, a total,
and JSON only where --json says (or on a pipe, as scripts read it)."""
from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.infer.reporting import WARNING_CHARS, Answer, Tally, camera_of
from cuboidtrain.infer.run import json_destination
from tests.test_infer import checkpoints, random_models, rectangles, write_png  # noqa: F401 (fixtures)

SEAM = ("the twobox cuboid explained the input better (IoU 0.950 against 0.903) but was set aside: its two parts' "
        "heights differ by 3% (< 10%): a box with a seam")


def box_record(**changes) -> dict:
    """A box's record as `infer` writes it with the cuboid fit (docs/contract.md), numbers as they come."""
    record = {"input": "masks/a.png", "shape": "box", "confidence": 0.9027, "keypoints": [[0.0, 0.0]] * 8,
              "ratios": {"depth_height": 0.3859, "width_height": 0.8999},
              "ratios_sd": {"depth_height": 0.1807, "width_height": 0.1803}, "refine_steps": 1,
              "refine_converged": True, "error": None, "warnings": [], "candidates": {"box": 0.9027, "twobox": 0.9058},
              "cuboid": {"yaw_deg": 7.2068, "yaw_sd_deg": 4.1085, "intrinsics": {"focal_px": "fitted",
                                                                                  "principal_px": "fitted"}}}
    return record | changes


def twobox_record(**changes) -> dict:
    part = {"right": {"depth_height": 1.571, "width_height": 1.349}, "left": {"depth_height": 3.803, "width_height": 2.251}}
    sd = {"right": {"depth_height": 0.361, "width_height": 0.271}, "left": {"depth_height": 0.879, "width_height": 0.468}}
    return box_record(input="b.png", shape="twobox", ratios=part, ratios_sd=sd, keypoints=[[0.0, 0.0]] * 14,
                      cuboid={"yaw_deg": -4.4, "yaw_sd_deg": 2.6, "intrinsics": {"focal_px": "given",
                                                                                  "principal_px": "fitted"}}) | changes


def test_a_box_records_line_has_its_fields():
    line = Answer.of(box_record()).line()
    assert line == ("masks/a.png  box  conf 0.90  d/h 0.39 ± 0.18  w/h 0.90 ± 0.18  yaw 7° ± 4°  camera fitted  "
                    "no warnings")


def test_a_twobox_records_line_has_each_parts_ratios_and_the_camera_given():
    line = Answer.of(twobox_record(warnings=[SEAM, "another"])).line()
    assert line.startswith("b.png  twobox  conf 0.90  d/h R 1.57 ± 0.36 / L 3.80 ± 0.88  "
                           "w/h R 1.35 ± 0.27 / L 2.25 ± 0.47  yaw -4° ± 3°  focal given, centre fitted  2 warnings: ")
    first = line.split("2 warnings: ")[1]
    assert first.endswith("…") and len(first) <= WARNING_CHARS + 1 and SEAM.startswith(first[:-1])


def test_the_trust_is_shown_where_the_record_has_one_else_the_confidence():
    assert "  trust low 0.21  " in Answer.of(box_record(trust={"level": "low", "score": 0.214})).line()
    assert "  conf 0.90  " in Answer.of(box_record()).line()


def test_a_networks_only_record_and_an_error_read_plainly():
    networks = box_record()
    del networks["ratios_sd"], networks["cuboid"]
    assert Answer.of(networks).line() == "masks/a.png  box  conf 0.90  d/h 0.39  w/h 0.90  no cuboid fit  no warnings"
    failed = box_record(shape=None, error="masks/a.png: cannot read image (No such file or directory)")
    assert Answer.of(failed).line() == "masks/a.png  error: masks/a.png: cannot read image (No such file or directory)"
    assert Answer.of(box_record(component=1)).line().startswith("masks/a.png #1  box  ")


def test_lines_of_a_run_are_aligned_column_by_column():
    widths = [12, 6, 17, 33, 33, 13]
    lines = [Answer.of(r).line(widths) for r in (box_record(), twobox_record())]
    starts = [[line.index(word) for word in ("conf", "d/h", "w/h", "yaw")] for line in lines]
    assert starts[0] == starts[1]


def test_the_total_counts_inputs_shapes_failures_warnings_and_trust():
    tally = Tally(total=4)
    tally.add([box_record(trust={"level": "high", "score": 0.9})])
    tally.add([twobox_record(warnings=[SEAM], trust={"level": "low", "score": 0.2})])
    tally.add([box_record(shape=None, error="gone")])
    tally.resume([box_record(warnings=["w"], trust={"level": "high", "score": 0.8})])
    assert (tally.done, tally.resumed, tally.failed, tally.warned) == (3, 1, 1, 2)
    summary = tally.summary()
    assert summary.startswith("4 masks (1 already in OUT); fitted 2 in ")  # 3 tried, 1 of them failed
    assert summary.endswith("records by shape: box 2, twobox 1; 1 failed; 2 with warnings; trust high 2, low 1")
    one = Tally(total=1)
    one.add([box_record()])
    assert one.summary().startswith("1 mask; ") and "trust" not in one.summary()


def test_json_goes_where_json_says_and_to_a_pipe_by_default_but_not_to_a_terminal():
    assert json_destination("-", None, terminal=True) == "-"
    assert json_destination("out.json", None, terminal=False) == "out.json"
    assert json_destination(None, "city.jsonl", terminal=False) is None
    assert json_destination(None, None, terminal=False) == "-"  # a script's pipe reads the list, as before
    assert json_destination(None, None, terminal=True) is None  # a person reads the lines


def test_infer_prints_a_line_per_input_and_the_total_and_json_only_on_stdout(tmp_path, checkpoints, monkeypatch):
    monkeypatch.chdir(tmp_path)
    paths = [Path(write_png(tmp_path / f"{k}.png", rectangles((60, 90), (10, 10, 70 - 9 * k, 50)))).name for k in range(2)]
    for json_args in (["--json", "-"], []):  # given, and the default without a terminal
        result = CliRunner().invoke(app, ["infer", *paths, "--checkpoint", str(checkpoints["box"]), *json_args])
        assert result.exit_code == 0, result.output
        records = json.loads(result.stdout)
        assert [r["input"] for r in records] == paths
        lines = [line for line in result.stderr.splitlines() if not line.startswith("20")]  # log lines aside
        assert [" ".join(line.split()) for line in lines[:2]] == [" ".join(Answer.of(r).line().split()) for r in records]
        assert lines[2].startswith("2 masks; fitted 2 in ") and "records by shape: box 2; 0 failed" in lines[2]


def test_the_line_says_where_each_intrinsic_came_from_exif_included():
    # a --photo's EXIF focal length is neither given nor fitted: the line says so (it read "camera fitted")
    assert camera_of({"focal_px": "exif", "principal_px": "exif"}) == "camera from EXIF"
    assert camera_of({"focal_px": "exif", "principal_px": "fitted"}) == "focal from EXIF, centre fitted"
    assert camera_of({"focal_px": "given", "principal_px": "exif"}) == "focal given, centre from EXIF"
    assert camera_of({"focal_px": "fitted", "principal_px": "given"}) == "centre given, focal fitted"
    assert camera_of({"focal_px": "given", "principal_px": "given"}) == "camera given"
    assert camera_of({"focal_px": "fitted", "principal_px": "fitted"}) == "camera fitted"
