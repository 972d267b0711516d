"""Masks given as fsspec URLs (cuboidtrain/fit/storage.py, inputs.py, masks.py): a URL folder is walked
as a local one is, a URL glob expanded, a list may name URLs, a mask read from a URL is the mask
read from the same file, and `infer` on URLs, in one process, with `--workers` and on a Dask
cluster, writes the local run's records but for `input`. `memory://` serves the tests in this
process, `file://` the ones across processes (a memory store is one process's). A local path
never imports fsspec. Skipped without fsspec (torch brings it; Dask too)."""
from __future__ import annotations

import json
import subprocess
import sys
import uuid
from importlib.util import find_spec
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app
from cuboidtrain.infer.inputs import gather_inputs
from cuboidtrain.fit.masks import load_mask
from shared.errors import UsageError
from tests.conftest import command_here, infer_paths, tiny_model, write_mask_pngs

fsspec = pytest.importorskip("fsspec")
ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


@pytest.fixture
def memory():
    """A fresh `memory://` folder, emptied afterwards (the memory store is the whole process's)."""
    root = f"memory://masks-{uuid.uuid4().hex[:8]}"
    yield root
    store = fsspec.filesystem("memory")
    if store.exists(root):
        store.rm(root, recursive=True)


def put(root: str, names: list[str], data: bytes = b"x") -> None:
    for name in names:
        fsspec.filesystem("memory").pipe(f"{root}/{name}", data)


def mirror(local: Path, root: str) -> None:
    """Copy a local folder's files into the memory folder `root`, at the same relative paths."""
    for path in local.rglob("*"):
        if path.is_file():
            put(root, [path.relative_to(local).as_posix()], path.read_bytes())


TREE = ["m/b.png", "m/a.PNG", "m/deep/er/c.jpg", "m/notes.txt", "m/.tmp-0-h-1-d.png", "m/.hidden/e.png",
        "m/x/roof_mask.png", "m/x/roof_photo.png"]


@pytest.mark.parametrize("glob", [None, "*_mask.png", "x/*.png"])
def test_a_url_folder_is_walked_as_the_same_local_folder_is(tmp_path, memory, glob):
    for name in TREE:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    mirror(tmp_path, memory)
    local = gather_inputs([str(tmp_path / "m")], glob=glob)
    for given in (f"{memory}/m", f"{memory}/m/"):
        assert gather_inputs([given], glob=glob) == [p.replace(str(tmp_path), memory) for p in local]


def test_a_url_glob_is_expanded_by_the_store_hidden_names_left_out_and_folders_walked(memory):
    put(memory, ["m/a.png", "m/b.png", "m/.c.png", "m/notes.txt", "m/d/e.png", "m/d/f.txt"])
    assert gather_inputs([f"{memory}/m/*.png"]) == [f"{memory}/m/a.png", f"{memory}/m/b.png"]
    assert gather_inputs([f"{memory}/m/*"]) == [f"{memory}/m/{n}" for n in ("a.png", "b.png", "d/e.png", "notes.txt")]


def test_a_list_may_name_urls_and_a_missing_one_refuses_it_whole(tmp_path, memory):
    put(memory, ["a.png", "d/b.png", "d/c.png"])
    listing = tmp_path / "list.txt"
    listing.write_text(f"# in the bucket\n{memory}/a.png\n{memory}/d/\n{memory}/d/*.png\n")
    assert gather_inputs([], from_list=str(listing)) == [f"{memory}/{n}" for n in ("a.png", "d/b.png", "d/c.png",
                                                                                   "d/b.png", "d/c.png")]
    listing.write_text(f"{memory}/a.png\n{memory}/gone.png\n{memory}/gone*.png\n")
    with pytest.raises(UsageError) as caught:
        gather_inputs([], from_list=str(listing))
    assert str(caught.value) == (f"--from-list {listing}: 2 of 3 listed paths do not exist "
                                 f"(first: {memory}/gone.png, {memory}/gone*.png); "
                                 f"expected existing mask files or folders")


def test_a_missing_url_among_others_goes_on_to_its_error_record(memory):
    put(memory, ["a.png"])
    assert gather_inputs([f"{memory}/a.png", f"{memory}/gone.png"]) == [f"{memory}/a.png", f"{memory}/gone.png"]


@pytest.mark.parametrize("given, glob, message", [
    ("{m}/empty/", None, "{m}/empty/: a folder with no files matching *.png, *.jpg"),
    ("{m}/full", "*.gif", "{m}/full: a folder with no files matching *.gif; expected mask images under it"),
    ("{m}/full/*.gif", None, "{m}/full/*.gif: nothing matches it; expected mask images"),
    ("{m}/nothing/", None, "{m}/nothing/: no such file; expected mask images"),
    ("s3://bucket/masks/", None, "s3://bucket/masks/: reading s3:// needs s3fs, which is not installed "
                                 "(Install s3fs to access S3); expected: pip install s3fs"),
    ("nosuch://bucket/x.png", None, "nosuch://bucket/x.png: Protocol not known: nosuch; expected a local path or a URL"),
])
def test_a_url_with_nothing_to_fit_is_one_line_naming_what_was_expected(memory, given, glob, message):
    if given.startswith("s3:") and find_spec("s3fs") is not None:
        pytest.skip("s3fs is installed here")
    put(memory, ["full/a.png", "empty/notes.txt"])
    with pytest.raises(UsageError) as caught:
        gather_inputs([given.format(m=memory)], glob=glob)
    assert str(caught.value).startswith(message.format(m=memory)) and "\n" not in str(caught.value)


def test_a_url_without_fsspec_is_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "fsspec", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "fsspec.core", None)
    with pytest.raises(UsageError, match=r"^s3://b/m/: reading a URL needs fsspec, which is not installed; "
                                         r"expected pip install 'cuboid-fit\[cluster\]'") as caught:
        gather_inputs(["s3://b/m/"])
    assert "\n" not in str(caught.value)


def test_cli_a_url_with_nothing_to_fit_is_one_line_before_any_model_loads(memory):
    put(memory, ["empty/notes.txt"])
    result = runner.invoke(app, ["infer", f"{memory}/empty/"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "a folder with no files matching" in lines[0], result.output


BLOB = np.zeros((40, 56), np.uint8)
BLOB[6:30, 10:44] = 1
BLOB[30:36, 20:30] = 1


@pytest.mark.parametrize("name, image, label_id", [
    ("grey.png", BLOB * 255, None),
    ("noisy.jpg", BLOB * 255, None),
    ("rgba.png", np.dstack([np.full((*BLOB.shape, 3), 90, np.uint8), BLOB * 255]), None),
    ("labels.png", BLOB * 11, 11),
])
def test_a_mask_read_from_a_url_is_the_mask_read_from_the_same_file(tmp_path, memory, name, image, label_id):
    path = tmp_path / name
    assert cv2.imwrite(str(path), image)
    put(memory, [name], path.read_bytes())
    assert (load_mask(f"{memory}/{name}", label_id) == load_mask(path, label_id)).all()


def test_a_url_that_cannot_be_read_is_that_input_s_error_as_a_file_s(tmp_path, memory):
    (tmp_path / "garbage.png").write_bytes(b"not an image")
    put(memory, ["garbage.png"], b"not an image")
    for name in ("garbage.png", "missing.png"):
        with pytest.raises(UsageError) as local:
            load_mask(tmp_path / name)
        with pytest.raises(UsageError) as remote:
            load_mask(f"{memory}/{name}")
        assert str(remote.value) == str(local.value).replace(str(tmp_path), memory)


def without_input(records: list[dict], given: str, instead: str) -> list[dict]:
    """Records with `input` dropped and the input's name in an error message put back to the local one."""
    return [{k: (v.replace(given, instead) if k == "error" and v else v) for k, v in r.items() if k != "input"}
            for r in records]


def test_records_of_urls_are_the_records_of_the_same_files_but_for_input(tmp_path, memory):
    paths = write_mask_pngs(tmp_path, 4)
    (tmp_path / "m002.png").write_text("not a picture")
    mirror(tmp_path, memory)
    urls = gather_inputs([memory])
    assert [u.replace(memory, str(tmp_path)) for u in urls] == paths
    models = [tiny_model("box"), tiny_model("twobox")]
    remote, local = infer_paths(urls, models), infer_paths(paths, models)
    assert [r["input"] for r in remote] == urls and remote[2]["error"]
    assert without_input(remote, memory, str(tmp_path)) == without_input(local, "", "")


def test_a_local_path_never_imports_fsspec(tmp_path):
    write_mask_pngs(tmp_path, 1)
    code = ("import sys; from cuboidtrain.infer.inputs import gather_inputs; from cuboidtrain.fit.masks import load_mask; "
            f"[load_mask(p) for p in gather_inputs([{str(tmp_path)!r}])]; print('fsspec' in sys.modules)")
    found = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert found.stdout.strip() == "False", found.stderr


# --- across processes: file:// URLs ----------------------------------------------------


@pytest.fixture(scope="module")
def masks(tmp_path_factory) -> list[str]:
    """8 generated masks of 64 to 128 px, box and twobox."""
    return write_mask_pngs(tmp_path_factory.mktemp("masks"), 8)


def infer(*args: str) -> subprocess.CompletedProcess:
    """`infer ARGS --device cpu --networks-only` in this process: the URLs cross processes where
    `--workers` fit them, each worker reading its own."""
    return command_here(["infer", *args, "--device", "cpu", "--networks-only"])


def stored(out: Path) -> list[dict]:
    return sorted((json.loads(line) for line in out.read_text().splitlines()), key=lambda r: r["index"])


@pytest.fixture(scope="module")
def local_records(masks) -> list[dict]:
    """The local paths' records of one uninterrupted run in this process (as tests/test_batch.py shows,
    `infer --networks-only` writes these very records)."""
    from tests.test_cluster import run

    return run(masks)


def test_two_workers_read_file_urls_and_resume_a_store_keyed_by_url(tmp_path, masks, local_records):
    folder = Path(masks[0]).parent
    url = folder.as_uri() + "/"
    (listing := tmp_path / "first.txt").write_text("".join(f"{url}{Path(p).name}\n" for p in masks[:3]))
    first = infer("--from-list", str(listing), "--jsonl", str(tmp_path / "urls.jsonl"))
    assert first.returncode == 0, first.stderr
    resumed = infer(url, "--jsonl", str(tmp_path / "urls.jsonl"), "--workers", "2")
    assert resumed.returncode == 0 and "holds 3 of the 8 inputs" in resumed.stderr, resumed.stderr
    remote = stored(tmp_path / "urls.jsonl")
    assert [r["index"] for r in remote] == list(range(8))
    assert [r["input"] for r in remote] == [f"{url}{Path(p).name}" for p in masks]
    assert [{k: v for k, v in r.items() if k != "index"} for r in without_input(remote, "", "")] == without_input(
        local_records, "", "")


def test_a_dask_cluster_reads_file_urls_into_the_records_of_local_paths(masks, local_records):
    from tests.test_cluster import run

    urls = [Path(p).as_uri() for p in masks]
    # one worker process reads the URLs (tests/test_cluster.py shows two share the inputs as one does)
    remote = run(urls, workers=1, cluster="local")
    assert [r["input"] for r in remote] == urls
    assert without_input(remote, "", "") == without_input(local_records, "", "")
