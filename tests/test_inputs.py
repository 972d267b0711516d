"""What `infer` is asked to fit (cuboidtrain/infer/inputs.py): files, folders, --glob, --from-list, and
nothing to fit as one line naming what was expected."""
from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.infer.inputs import gather_inputs
from shared.errors import UsageError

runner = CliRunner()


def touch(*paths: Path) -> list[str]:
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x")
    return [str(p) for p in paths]


def test_a_folder_is_walked_recursively_in_sorted_order_for_images(tmp_path):
    b, a, c = touch(tmp_path / "m/b.png", tmp_path / "m/a.PNG", tmp_path / "m/deep/er/c.jpg")
    touch(tmp_path / "m/notes.txt", tmp_path / "m/.tmp-0-h-1-d.png", tmp_path / "m/.hidden/e.png")
    assert gather_inputs([str(tmp_path / "m")]) == [a, b, c]


def test_glob_picks_the_files_of_a_folder_and_files_given_stay_as_given(tmp_path):
    keep, = touch(tmp_path / "m/x/roof_mask.png")
    touch(tmp_path / "m/x/roof_photo.png")
    single = str(tmp_path / "single.tif")
    assert gather_inputs([single, str(tmp_path / "m")], glob="*_mask.png") == [single, keep]


def test_a_list_file_gives_paths_and_folders_one_a_line(tmp_path):
    first, second = touch(tmp_path / "a.png", tmp_path / "d/b.png")
    listing = tmp_path / "list.txt"
    listing.write_text(f"# masks of one street\n{first}\n\n  {tmp_path / 'd'}  \n")
    assert gather_inputs([], from_list=str(listing)) == [first, second]


def test_some_missing_inputs_go_on_to_their_error_records(tmp_path):
    good, = touch(tmp_path / "a.png")
    assert gather_inputs([good, str(tmp_path / "gone.png")]) == [good, str(tmp_path / "gone.png")]


def test_a_list_naming_missing_files_is_refused_whole_naming_the_first_few(tmp_path):
    good, = touch(tmp_path / "a.png")
    gone = [str(tmp_path / f"gone{i}.png") for i in range(4)]
    listing = tmp_path / "paths.txt"
    listing.write_text("\n".join([good, gone[0], good, *gone[1:]]) + "\n")
    with pytest.raises(UsageError) as caught:
        gather_inputs([], from_list=str(listing))
    assert str(caught.value) == (f"--from-list {listing}: 4 of 6 listed paths do not exist "
                                 f"(first: {gone[0]}, {gone[1]}, {gone[2]}, ...); "
                                 f"expected existing mask files or folders")


@pytest.mark.parametrize("setup, message", [
    (lambda t: ([str(t / "empty")], None, None), "a folder with no files matching *.png"),
    (lambda t: ([str(t / "full")], None, "*.gif"), "no files matching *.gif"),
    (lambda t: ([], str(t / "empty.txt"), None), "no paths in it; expected one mask path a line"),
    (lambda t: ([], str(t / "nope.txt"), None), "--from-list"),
    (lambda t: ([str(t / "gone.png"), str(t / "gone2.png")], None, None), "no such file (nor the 1 other"),
    (lambda t: ([], None, None), "expected mask PATHs"),
])
def test_nothing_to_fit_is_a_usage_error_naming_what_was_expected(tmp_path, setup, message):
    (tmp_path / "empty").mkdir()
    touch(tmp_path / "full/a.png")
    (tmp_path / "empty.txt").write_text("# nothing yet\n\n")
    paths, from_list, glob = setup(tmp_path)
    with pytest.raises(UsageError, match="expected") as caught:
        gather_inputs(paths, from_list, glob)
    assert message in str(caught.value)


@pytest.mark.parametrize("args, message", [
    (["{tmp}/empty"], "a folder with no files matching"),
    (["--from-list", "{tmp}/empty.txt"], "no paths in it"),
    (["{tmp}/full", "--glob", "*.gif"], "no files matching *.gif"),
    (["{tmp}/full", "--jsonl", "{tmp}/full/a.png/out.jsonl"], "--jsonl"),
    (["{tmp}/full", "--jsonl", "{tmp}/empty"], "--jsonl"),
    (["{tmp}/full", "--workers", "2", "--explain", "{tmp}/pics"], "expected --workers 1"),
    (["--from-list", "{tmp}/stale.txt", "--jsonl", "{tmp}/o.jsonl"],
     "--from-list {tmp}/stale.txt: 1 of 2 listed paths do not exist (first: {tmp}/full/gone.png); expected"),
    (["--from-list", "-", "--jsonl", "{tmp}/o.jsonl"], "--from-list stdin: 1 of 2 listed paths do not exist"),
])
def test_cli_nothing_to_fit_or_nowhere_to_write_is_one_line(tmp_path, args, message):
    (tmp_path / "empty").mkdir()
    touch(tmp_path / "full/a.png")
    (tmp_path / "empty.txt").write_text("\n")
    (tmp_path / "stale.txt").write_text(f"{tmp_path}/full/a.png\n{tmp_path}/full/gone.png\n")
    result = runner.invoke(app, ["infer"] + [a.format(tmp=tmp_path) for a in args],
                           input=(tmp_path / "stale.txt").read_text())
    message = message.format(tmp=tmp_path)
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], result.output
    assert not (tmp_path / "o.jsonl").exists()  # refused before any fit
