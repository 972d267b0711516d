"""Every numeric option of both daemons and every scene field: generated values (NaN, infinities,
negatives, huge numbers, wrong types) are either accepted and in range, or refused with a
UsageError naming the option or field (issue 22, defects 4, 5, 9, 11, 12).

The fields are walked with dataclasses.fields, so a field added later is covered, and a numeric
field added without a declared range fails `test_every_numeric_field_declares_its_range`."""
from __future__ import annotations

import json
import math
import numbers
from dataclasses import fields, replace

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from cuboidgen.config import SCENES, GenConfig, SceneConfig, load_scene, scene_from_dict
from cuboidgen.synth import make_sample
from cuboidtrain.fit.options import FitOptions, parse_refine_steps
from cuboidtrain.models.settings import MAX_REFINE_STEPS
from cuboidtrain.train.config import TrainConfig
from shared.checks import bounds_of, is_pair, max_processes, option_name
from shared.errors import UsageError

FAST = settings(max_examples=25, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

SPECIAL = [math.nan, math.inf, -math.inf, -1, -1.0, 0, 0.0, 0.5, 1, 1e-300, 1e300, 10**30, -(10**30), 2**63, True]
# What a user or a file may put where a number belongs: numbers of every size, and other types.
NUMBERS = st.one_of(
    st.sampled_from(SPECIAL),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(0, 1),
    st.floats(-200, 200),
    st.integers(-(10**20), 10**20),
    st.integers(-3, 300),
)
WRONG_TYPES = st.one_of(st.none(), st.text(max_size=4), st.lists(st.integers(), max_size=3), st.booleans(),
                        st.dictionaries(st.text(max_size=2), st.integers(), max_size=1))
VALUES = st.one_of(NUMBERS, WRONG_TYPES)
# A scene field's range as a JSON/TOML file may hold it: a pair of anything, a wrong length, a non-list.
FINITE = st.one_of(st.floats(0, 1), st.floats(-200, 200), st.integers(0, 70))
PAIRS = st.one_of(st.lists(FINITE, min_size=2, max_size=2).map(sorted), st.lists(NUMBERS, min_size=2, max_size=2),
                  st.lists(VALUES, min_size=0, max_size=3), VALUES)

# Each config: a valid instance to vary one field of, and how its error names the field.
TRAIN = TrainConfig(arch="tiny", size=32)
GEN = GenConfig(workers=1, size=32)
FIT = FitOptions(device="cpu")
CONFIGS = {"train": TRAIN, "gen": GEN, "fit": FIT}
PARSED = {("fit", "refine_steps"), ("fit", "pdm_components"),  # strings parsed by their own functions (tested below)
          ("fit", "principal_px")}  # a point (x, y), any finite numbers: FitOptions._check_camera (tests/test_camera_fit.py)


def numeric_fields(cls) -> list[str]:
    """Fields whose type holds a number (bool aside): int, float, or a Range of them."""
    names = []
    for f in fields(cls):
        kind = str(f.type)
        if any(word in kind for word in ("int", "float", "Range")) and kind != "bool":
            names.append(f.name)
    return names


@pytest.mark.parametrize("cls", [TrainConfig, GenConfig, FitOptions, SceneConfig])
def test_every_numeric_field_declares_its_range(cls):
    declared = set(bounds_of(cls))
    key = {TrainConfig: "train", GenConfig: "gen", FitOptions: "fit"}.get(cls)
    missing = [n for n in numeric_fields(cls) if n not in declared and (key, n) not in PARSED]
    assert not missing, f"{cls.__name__}: numeric fields without a declared range (shared.checks.number): {missing}"


def in_range(value, bounds) -> bool:
    """Independently of `Bounds.accepts`: a real, finite number (or an allowed None) within the bounds."""
    if value is None:
        return bounds.optional
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        return False
    if bounds.integer and value != int(value):
        return False
    return ((bounds.lo is None or value > bounds.lo or (value == bounds.lo and not bounds.lo_open))
            and (bounds.hi is None or value < bounds.hi or (value == bounds.hi and not bounds.hi_open)))


def accepted_or_named(config, name: str, value, option: str) -> bool:
    """True if `config` with `name` = `value` validates (value in its range), False if refused
    with a UsageError naming `option`; anything else fails the test."""
    try:
        config = replace(config, **{name: value}).validate()
    except UsageError as exc:
        assert str(exc).startswith(option + " ") or f"{option} " in str(exc), (name, value, str(exc))
        assert "\n" not in str(exc)
        return False
    return True


OPTION_FIELDS = [(key, name) for key, config in CONFIGS.items() for name in bounds_of(config)]


@pytest.mark.parametrize("key, name", OPTION_FIELDS)
@FAST
@given(value=VALUES)
def test_every_numeric_option_is_finite_and_in_range_or_named(key, name, value):
    config = CONFIGS[key]
    bounds = bounds_of(config)[name]
    if accepted_or_named(config, name, value, option_name(name)):
        assert in_range(value, bounds), f"{option_name(name)} {value!r} accepted, outside {bounds.expected()}"


@pytest.mark.parametrize("key, name", OPTION_FIELDS)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, "1", [1], True])
def test_non_finite_and_wrong_types_are_always_refused(key, name, value):
    assert not accepted_or_named(CONFIGS[key], name, value, option_name(name))


@pytest.mark.parametrize("name", list(bounds_of(TrainConfig)))
def test_the_defaults_are_in_their_own_ranges(name):
    assert in_range(getattr(TrainConfig(), name), bounds_of(TrainConfig)[name])


@FAST
@given(value=st.one_of(VALUES, st.sampled_from(["auto", "3", "16", "17", "1000000", " 2", "-1", "1.5"])))
def test_refine_steps_are_capped_as_auto_is(value):
    try:
        steps = parse_refine_steps(value)
    except UsageError as exc:
        assert str(exc).startswith("--refine-steps ") and str(MAX_REFINE_STEPS) in str(exc)
        return
    assert steps is None or (isinstance(steps, int) and 0 <= steps <= MAX_REFINE_STEPS)


def test_refine_steps_beyond_the_cap_are_refused():
    assert parse_refine_steps(str(MAX_REFINE_STEPS)) == MAX_REFINE_STEPS
    with pytest.raises(UsageError, match=rf"--refine-steps '1000000': expected .* 0 to {MAX_REFINE_STEPS}"):
        FitOptions(refine_steps="1000000").validate()


@FAST
@given(value=st.one_of(VALUES, st.sampled_from(["inf", "nan", "1e400", "6", "0.999", "-3"])))
def test_pdm_components_are_a_count_or_a_fraction_or_named(value):
    try:
        parsed = replace(FIT, pdm_components=value).validate().pdm_components
    except UsageError as exc:
        assert str(exc).startswith("--pdm-components ")
        return
    assert math.isfinite(parsed) and (0 < parsed < 1 or (parsed >= 1 and parsed == int(parsed)))


# ---- scene files ----------------------------------------------------------------------------

SCENE_FIELDS = [f.name for f in fields(SceneConfig) if f.name != "name"]
LIBRARY = None


def library():
    global LIBRARY
    if LIBRARY is None:
        from cuboidgen.occluders import OccluderLibrary

        LIBRARY = OccluderLibrary.builtin(variants_per_kind=2, seed=0)
    return LIBRARY


def sample_is_sound(scene: SceneConfig, size: int = 32, refusal_ok: bool = True) -> None:
    """Accepted scenes draw samples with finite keypoints on the image (margin 0 reaches its far edge),
    or (with `refusal_ok`) are refused in one line when their boxes cannot be put in front of the camera."""
    for shape in ("box", "twobox"):
        try:
            sample = make_sample(shape, scene, size, 7, library())
        except UsageError as exc:
            assert str(exc).startswith(f"scene {scene.name!r}: ")
            if not refusal_ok:
                raise AssertionError(f"the preset {scene.name!r} is refused: {exc}") from exc
            return
        k = sample.keypoints
        assert np.isfinite(k).all() and k.min() >= -1e-6 and k.max() <= size + 1e-6, (scene, k)


@pytest.mark.parametrize("name", SCENE_FIELDS)
@FAST
@given(value=PAIRS)
def test_every_scene_field_is_checked_or_named(name, value):
    bounds = bounds_of(SceneConfig)[name]
    try:
        scene = scene_from_dict({name: value}, default_name="probe")
    except UsageError as exc:
        assert str(exc).startswith(f"scene 'probe': {name} "), str(exc)
        assert "\n" not in str(exc)
        return
    given_value = getattr(scene, name)
    if is_pair(SceneConfig, name) and given_value is not None:
        lo, hi = given_value
        assert in_range(lo, bounds) and in_range(hi, bounds) and lo <= hi
    else:
        assert in_range(given_value, bounds)
    event("accepted")
    sample_is_sound(scene)


def within(bounds):
    """Values a field's declared range accepts (the strategy for whole scenes drawn inside the bounds)."""
    if bounds.integer:
        return st.integers(int(bounds.lo), int(bounds.hi))
    return st.floats(bounds.lo, bounds.hi, exclude_min=bounds.lo_open, exclude_max=bounds.hi_open)


@st.composite
def scenes(draw):
    values = {}
    for name, bounds in bounds_of(SceneConfig).items():
        if is_pair(SceneConfig, name):
            values[name] = None if bounds.optional and draw(st.booleans()) else tuple(sorted(draw(st.lists(
                within(bounds), min_size=2, max_size=2))))
        else:
            values[name] = draw(within(bounds))
    return SceneConfig(name="drawn", **values)


@FAST
@given(scene=scenes())
def test_scenes_inside_every_declared_range_draw_sound_samples_or_are_refused(scene):
    sample_is_sound(scene.validate())


@pytest.mark.parametrize("text", [
    "[1, 2, 3]", '"paper"', "null", '{"width": "wide"}', '{"width": [NaN, 1.0]}', '{"distance": [Infinity, Infinity]}',
    '{"margin": [-1, -0.5]}', '{"occluders": [-3, -1]}', '{"occluders": [0.5, 2]}', '{"width": {"lo": 1}}',
    '{"base": ["paper"]}', '{"name": 3}', '{"flip_probability": NaN}', '{"split": [0.3, 0.7, 0.9]}',
])
def test_bad_scene_files_are_one_line_usage_errors(tmp_path, text):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(UsageError) as info:
        load_scene(str(path))
    assert "\n" not in str(info.value) and str(info.value).startswith("scene ")


def test_a_scene_whose_boxes_reach_behind_the_camera_is_refused_not_looped_on():
    scene = replace(SCENES["paper"], name="inside", depth=(50.0, 50.0), distance=(1.0, 1.0))
    scene.validate()  # each field is in range; together they cannot be drawn
    with pytest.raises(UsageError, match="scene 'inside': 1000 box draws in a row"):
        make_sample("box", scene, 32, 0, library())


@pytest.mark.parametrize("preset", list(SCENES.values()), ids=list(SCENES))
def test_presets_are_valid(preset):
    """A preset is never refused: it validates and draws sound samples of both shapes, at two sizes."""
    from cuboidgen.scene import check_drawable
    from shared.shapes import SHAPES, get_shape

    assert preset.validate() == preset
    check_drawable(preset, [get_shape(name) for name in SHAPES], 256)  # as `cuboidgen run` checks at start-up
    for size in (32, 256):
        sample_is_sound(preset, size, refusal_ok=False)


# ---- the command lines: one line naming the option ------------------------------------------

def one_line(result) -> str:
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    return lines[0]


@pytest.mark.parametrize("args, expected", [
    (["--workers", "1000"], f"--workers 1000: expected an integer from 1 to {max_processes()} (4 per core"),
    (["--size", "100000"], "--size 100000: expected an integer from 16 to 4096 (px)"),
    (["--seed", "-1"], "--seed -1: expected an integer from 0 to"),
    (["--max-rate", "nan"], "--max-rate nan: expected a finite number > 0"),
    (["--evict-every", "0"], "--evict-every 0: expected an integer >= 1"),
])
def test_cuboidgen_run_refuses_in_one_line(tmp_path, args, expected):
    from cuboidgen.cli import app

    result = CliRunner().invoke(app, ["run", "--spool", str(tmp_path / "s"), "--no-dashboard", *args])
    assert expected in one_line(result)
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("text, expected", [
    ('{"width": [NaN, 1.0]}', "scene 'bad': width (nan, 1.0): expected a range (min, max) with min <= max"),
    ('{"distance": [Infinity, Infinity]}', "scene 'bad': distance (inf, inf): expected a range"),
    ("[1, 2, 3]", "scene 'bad': expected a table of fields (a JSON object), not list"),
    ('{"width": "wide"}', "scene 'bad': width 'wide': expected a range"),
])
def test_cuboidgen_run_refuses_a_bad_scene_file_in_one_line(tmp_path, text, expected):
    from cuboidgen.cli import app

    (tmp_path / "bad.json").write_text(text)
    result = CliRunner().invoke(app, ["run", "--spool", str(tmp_path / "s"), "--no-dashboard",
                                      "--scene", str(tmp_path / "bad.json")])
    assert expected in one_line(result)


def test_cuboidgen_run_refuses_an_undrawable_scene_in_one_line(tmp_path):
    from cuboidgen.cli import app

    scene = tmp_path / "inside.json"
    scene.write_text(json.dumps({"depth": [50, 50], "distance": [1, 1]}))
    result = CliRunner().invoke(app, ["run", "--spool", str(tmp_path / "s"), "--no-dashboard", "--scene", str(scene)])
    assert "scene 'inside': 1000 box draws in a row" in one_line(result)


def test_cuboidgen_run_names_an_unwritable_spool(tmp_path, monkeypatch):
    from cuboidgen.cli import app

    (tmp_path / "noperm").mkdir(mode=0o555)
    monkeypatch.setattr("os.access", lambda path, mode, **k: False)  # as an unprivileged user: root ignores modes
    monkeypatch.setattr("pathlib.Path.mkdir", lambda *a, **k: (_ for _ in ()).throw(PermissionError(13, "Permission denied")))
    result = CliRunner().invoke(app, ["run", "--spool", str(tmp_path / "noperm" / "sub"), "--no-dashboard", "--workers", "1"])
    assert one_line(result) == f"error: spool {tmp_path / 'noperm' / 'sub'}: cannot create it (Permission denied)"


@pytest.mark.parametrize("args, expected", [
    (["--lr", "nan"], "--lr nan: expected a finite number > 0"),
    (["--lr", "inf"], "--lr inf: expected a finite number > 0"),
    (["--sigma", "nan"], "--sigma nan: expected a finite number > 0"),
    (["--ratio-weight", "nan"], "--ratio-weight nan: expected a finite number >= 0"),
    (["--phase", "2", "--alpha-t", "nan"], "--alpha-t nan: expected a finite number >= 0"),
    (["--alpha-r", "-1"], "--alpha-r -1.0: expected a finite number >= 0"),
    (["--max-minutes", "nan"], "--max-minutes nan: expected a finite number > 0"),
    (["--max-wait", "nan"], "--max-wait nan: expected a finite number > 0"),
    (["--seed", "-1"], "--seed -1: expected an integer from 0 to"),
    (["--size", "100000"], "--size 100000: expected an integer from 32 to 2048 (px)"),
    (["--loader-workers", "1000"], f"--loader-workers 1000: expected an integer from 0 to {max_processes()}"),
])
def test_cuboidtrain_run_refuses_in_one_line(tmp_path, args, expected):
    from cuboidtrain.cli import app

    result = CliRunner().invoke(app, ["run", "--spool", str(tmp_path), "--out", str(tmp_path / "run"),
                                      "--arch", "tiny", "--size", "32", "--no-dashboard", *args])
    assert expected in one_line(result)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("args, expected", [
    (["--refine-steps", "1000000"], f"--refine-steps '1000000': expected a whole number of passes from 0 to {MAX_REFINE_STEPS}"),
    (["--margin", "nan"], "--margin nan: expected a finite number >= 0 and < 0.5"),
])
def test_infer_refuses_in_one_line(tmp_path, args, expected):
    from cuboidtrain.cli import app

    result = CliRunner().invoke(app, ["infer", str(tmp_path / "none.png"), "--device", "cpu", *args])
    assert expected in one_line(result)
