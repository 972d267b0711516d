"""docs/contract.md against the code: its corner tables, infer record fields and sample fields
are what the code defines, so the page cannot drift from it unnoticed."""
import json
import re
from pathlib import Path

import cv2
import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app
from shared.sample import decode_record, encode
from shared.shapes import SHAPES, TWOBOX
from tests.conftest import build_sample

ROOT = Path(__file__).resolve().parents[1]
CONTRACT = ROOT / "docs" / "contract.md"


def section(title: str) -> str:
    """The text under the heading `title` (any level) up to the next heading of that level or above."""
    text = CONTRACT.read_text()
    match = re.search(rf"^(#+) {re.escape(title)}\n", text, re.MULTILINE)
    assert match, f"docs/contract.md has no heading {title!r}"
    level = len(match.group(1))
    end = re.search(rf"^#{{1,{level}}} ", text[match.end():], re.MULTILINE)
    return text[match.end(): match.end() + end.start() if end else len(text)]


def table_rows(text: str) -> list[list[str]]:
    """The body rows of the markdown tables in `text`, as stripped cells."""
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("|")]
    return [r for r in rows if not set("".join(r)) <= set("-: ") and r[0] not in ("index", "field", "key", "term")]


def documented_keys(title: str) -> list[str]:
    return [re.fullmatch(r"`([a-z_0-9]+)`", row[0]).group(1) for row in table_rows(section(title))]


@pytest.mark.parametrize("shape, title", [("box", "box: 8 keypoints, the paper's Table 1"),
                                          ("twobox", "twobox: 14 keypoints, the paper's Table 2")])
def test_corner_tables_are_the_shapes_keypoints_in_order(shape, title):
    rows = table_rows(section(title))
    assert [(int(i), name) for i, name in rows] == list(enumerate(SHAPES[shape].keypoint_names))
    assert str(SHAPES[shape].num_keypoints) in title


def test_twobox_parts_are_the_documented_ones():
    text = " ".join(section("twobox: 14 keypoints, the paper's Table 2").split())
    for part, name in zip(TWOBOX.parts, TWOBOX.part_names):
        assert f"`{name}` is `{list(part)}`" in text


def test_the_figure_is_there_and_shown():
    assert (ROOT / "docs" / "keypoints.png").is_file()
    assert "](keypoints.png)" in section("Keypoints")


def infer_json(paths, *options) -> list[dict]:
    """The records `cuboidtrain infer` writes (the shipped models), read back from its JSON file."""
    out = paths[0].with_name(f"records{len(options)}.json")
    result = CliRunner().invoke(app, ["infer", *map(str, paths), *options, "--json", str(out)])
    assert result.exit_code == 1, (result.output, result.exception)  # 1: the missing file's record has an error
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """Real records: a fitted mask and a missing file, networks only with and without --all-components,
    and infer's default (the cuboid fit)."""
    folder = tmp_path_factory.mktemp("infer")
    mask = folder / "mask.png"
    assert cv2.imwrite(str(mask), build_sample(0, size=64).clean.astype("uint8") * 255)
    paths = [mask, folder / "missing.png"]
    return infer_json(paths, "--networks-only"), infer_json(paths, "--networks-only", "--all-components"), infer_json(paths)


def test_every_record_field_is_documented_and_every_documented_field_is_written(records):
    plain, per_component, cuboid = records
    assert [r["error"] is None for r in plain] == [True, False]  # a fit and an error record
    documented = documented_keys("The infer record")
    assert len(documented) == len(set(documented))
    for record in plain + per_component + cuboid:
        assert set(record) <= set(documented), set(record) - set(documented)
    assert set().union(*per_component, *cuboid) == set(documented)
    # the optional fields are the ones the table says are optional
    assert {k for k in documented if not all(k in r for r in plain)} == {"component", "cuboid", "ratios_sd", "trust", "shape_call"}
    assert "only with `--all-components`" in section("The infer record")
    assert "not with `--networks-only`" in section("The infer record")


def test_the_cuboid_object_is_documented(records):
    fitted, failed = records[2]
    assert failed["cuboid"] is None
    assert list(fitted["cuboid"]) == documented_keys("The cuboid object (`infer`, unless `--networks-only`)")
    assert set(fitted["cuboid"]["corners"][0]) == {"on_outline", "score"}


@pytest.mark.parametrize("shape", ["box", "twobox"])
def test_sample_fields_and_params_are_documented(shape):
    import msgpack

    data = encode(build_sample(0, shape))
    outer = msgpack.unpackb(data)
    record = decode_record(data)
    # two tables: the file's map, then its payload's fields (the same keys, in encoding order)
    documented = documented_keys("Sample format (version 3)")
    assert documented == list(outer) + list(msgpack.unpackb(outer["payload"]))
    assert list(record) == ["format", "version", *msgpack.unpackb(outer["payload"])]
    params_row = next(r for r in table_rows(section("Sample format (version 3)")) if r[0] == "`params`")
    named = set(re.findall(r"`([a-z_]+)`", params_row[2]))
    assert set(record["params"]) - {"eye_height"} <= named
    assert "eye_height" in named  # standing scenes (street) add it
