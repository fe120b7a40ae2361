"""One schema for every config file (issue 8, section 3; issue 7, section 6 "Bad input").

Oracles independent of the code under test: the JSON Schema checked by the `jsonschema`
package (another implementation than pydantic), the YAML files parsed by PyYAML directly,
and hand-written expected values.
"""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest
import yaml

from harvest_qp.cli import main
from harvest_qp.config import config_reference_markdown, json_schema, load_config, resolve_file
from harvest_qp.config.episode_schema import EpisodeConfig
from harvest_qp.config.settings import DEFAULTS, load_settings
from harvest_qp.config.task_schema import TaskConfig
from harvest_qp.exceptions import ConfigError, HarvestQPError
from harvest_qp.robot.paths import tasks_dir

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted(tasks_dir().glob("*.yaml")) + sorted((ROOT / "examples").glob("*.yaml"))


@pytest.fixture(scope="module")
def validator():
    """The generated JSON Schema (the shipped file is checked equal to it below) in `jsonschema`."""
    schema = json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_shipped_schema_and_reference_are_generated_from_the_schema():
    """Catches: a key added to the models without `harvest-qp schema --out tasks/schema.json
    --markdown docs/config.md` (editors would then flag a valid key, the docs would lie)."""
    assert json.loads((tasks_dir() / "schema.json").read_text()) == json_schema()
    assert (ROOT / "docs" / "config.md").read_text() == config_reference_markdown()


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_config_passes_check_config_and_the_json_schema(path, validator, capsys):
    """Each tasks/*.yaml (and examples/*.yaml) passes `harvest-qp check-config` (builds its tasks and limits), the
    exported JSON Schema as checked by `jsonschema`, and names the schema for editors.

    Catches: a shipped file that drifted from the schema, or an export that rejects valid files."""
    assert main(["check-config", str(path)]) == 0, capsys.readouterr().err
    assert ": OK" in capsys.readouterr().out
    header = path.read_text().splitlines()[0]
    assert header.startswith("# yaml-language-server: $schema=") and header.endswith("schema.json")
    assert (path.parent / header.split("=", 1)[1]).resolve() == (tasks_dir() / "schema.json").resolve()
    resolved = resolve_file(path)  # after extends: what the file means
    errors = [e.message for e in validator.iter_errors(resolved.data)]
    assert not errors, errors


@pytest.mark.parametrize(
    "data",
    [
        {"grasping": {"k_pq": 0.1}},  # unknown key
        {"grasping": {"k_fp": -0.001}},  # out of range
        {"grasping": {"r_o": "m"}},  # neither a number nor 'l'
        {"camera": {"width": 848.5}},  # not an integer
        {"camera": {"dropout": 1.0}},  # fraction must be < 1
        {"qp": {"camera_task": {"weight": [1, 1, 1]}}},  # 3 weights for a 6-D task
        {"qp": {"limits": [{"type": "joint_velocity", "max_velocity": 1.0, "gain": 2}]}},  # option of another limit
        {"mapper": {"kind": "svd"}},
        {"tasks": []},
        {"tasks": [{"type": "frame_pose"}]},  # frame missing
        {"tasks": [{"type": "damping", "gain": 1.0}]},  # damping has no gain
    ],
)
def test_pydantic_and_the_exported_json_schema_reject_the_same_bad_files(data, validator):
    """Catches: a constraint that exists in the models but not in the JSON Schema (or the
    reverse), e.g. ``extra='forbid'`` or a bound lost in the export."""
    assert list(validator.iter_errors(data)), data
    with pytest.raises(ConfigError):
        load_config_from(data)


def load_config_from(data, tmp=None):
    from harvest_qp.config import validate_data

    return validate_data(data, source="inline")


def _leaves(node, prefix=()):
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, (*prefix, key))
    else:
        yield prefix, node


def test_the_settings_the_loop_reads_are_the_values_of_paper_yaml():
    """Every value written in tasks/paper.yaml (parsed by PyYAML, the oracle) reaches the
    controller's settings dict unchanged under the same key, and the defaults equal the file.

    Catches: a key renamed, dropped or shadowed by a default in the schema, i.e. an
    episode that would differ from the one `harvest-qp run tasks/paper.yaml` gave before."""
    raw = yaml.safe_load((tasks_dir() / "paper.yaml").read_text())
    settings = load_settings(tasks_dir() / "paper.yaml").model_dump()
    for keys, value in _leaves(raw):
        got = settings
        for key in keys:
            got = got[key]
        if keys == ("qp", "limits"):  # entries gain their class defaults (gain 0.95, max_pairs 24, ...)
            for entry, checked in zip(value, got, strict=True):
                assert {k: checked[k] for k in entry} == entry
            continue
        assert got == value, keys
    for keys, value in _leaves({k: v for k, v in raw.items() if k != "description"}):
        got = DEFAULTS.model_dump()
        for key in keys:
            got = got[key]
        if keys != ("qp", "limits"):
            assert got == value, keys


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("grasping:\n  k_pq: 0.1\n", ["unknown key 'grasping.k_pq'", "did you mean 'k_pg'"]),
        ("grasping:\n  k_fp: -0.001\n", ["'grasping.k_fp' must be a number > 0", "got -0.001"]),
        ("grasping:\n  k_fp: 1e-3\n", ["'grasping.k_fp'", "got '1e-3'", "write 1.0e-3"]),
        ("unveiling: {enabled: 1}\n", ["'unveiling.enabled'", "true or false", "got 1"]),
        ("qp: {camera_task: {level: 0}}\n", ["'qp.camera_task.level' must be an integer >= 1", "got 0"]),
        ("qp: {limits: [{type: colision}]}\n", ["'qp.limits[0].type'", "did you mean 'collision'"]),
        ("qp: {limits: [{type: collision, gain: -1}]}\n", ["'qp.limits[0].gain' must be a number > 0", "got -1"]),
        ("obstacle_map: {arms: all}\n", ["'obstacle_map.arms' must be one of: camera, both", "got 'all'"]),
        ("scene: {params: {stem_lenght: 0.1}}\n", ["'scene.params.stem_lenght'", "did you mean 'stem_length'"]),
        ("scene: {params: {stem_length: -1.0}}\n", ["'scene.params'", "stem_length must be a finite number > 0",
                                                     "got -1.0"]),
        ("tasks: [{type: posture, wieght: 1.0}]\n", ["unknown key 'tasks[0].wieght'", "did you mean 'weight'"]),
        ("dt: 0.002\ntasks: [{type: frame_twist, frame: camera, weight: [1, 2]}]\n",
         ["'tasks[0].weight' must be a number >= 0 or a list of 6 numbers >= 0", "got [1, 2]"]),
        ("grasping: {f_d: 2}\ngrasping: {f_d: 3}\n", ["not valid YAML at line 2", "'grasping' given twice"]),
        ("!!python/object/apply:os.system ['echo unsafe']\n", ["not valid YAML", "python/object"]),
        ("just text\n", ["must hold a mapping", "got str"]),
        ("a: [unclosed\n", ["not valid YAML"]),
    ],
)
def test_a_bad_file_gives_one_line_naming_file_key_value_and_expectation(tmp_path, capsys, text, words):
    """`harvest-qp check-config` on a bad file: exit code 2, one line on stderr, no traceback,
    the file, the key path, the bad value, what was expected (and the nearest valid key).

    Catches: a traceback, a silently ignored key, a message without the file or the path."""
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert str(path) in err, err
    for word in words:
        assert word in err, (word, err)


def test_a_binary_file_and_a_missing_file_are_config_errors(tmp_path, capsys):
    binary = tmp_path / "model.bin"
    binary.write_bytes(bytes(range(256)) * 4)
    assert main(["check-config", str(binary)]) == 2
    err = capsys.readouterr().err
    assert str(binary) in err and err.count("\n") == 1
    assert main(["check-config", str(tmp_path / "nope.yaml")]) == 2
    assert "file not found" in capsys.readouterr().err
    assert issubclass(ConfigError, HarvestQPError)


def test_a_file_of_the_other_kind_is_named_as_such(tmp_path, capsys):
    """`run` on a QP task config and `demo` on an episode config say which kind the file is.

    Catches: a wall of "unknown key" errors (or a traceback) for using the wrong sub-command."""
    assert main(["run", str(tasks_dir() / "reach_targets.yaml"), "--out", str(tmp_path)]) == 2
    assert "this is a QP task configuration" in capsys.readouterr().err
    assert main(["demo", "--kinematic", "--config", str(tasks_dir() / "paper.yaml")]) == 2
    assert "this is an episode configuration" in capsys.readouterr().err
    no_tasks = tmp_path / "no_tasks.yaml"
    no_tasks.write_text("{}\n")
    assert main(["demo", "--kinematic", "--config", str(no_tasks)]) == 2
    assert "'tasks' is required" in capsys.readouterr().err


@pytest.mark.parametrize("text", ["", "\n\n", "# nothing but a comment\n"])
def test_an_empty_file_is_refused_not_run_as_defaults(tmp_path, capsys, text):
    """A blank or comment-only config file is an error naming the file; ``{}`` takes the defaults.

    Catches: an empty file (a bad copy, a wrong path written over) silently running the
    paper episode with every default, as the previous session's audit found."""
    empty = tmp_path / "empty.yaml"
    empty.write_text(text)
    assert main(["run", str(empty), "--duration", "0.01", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert str(empty) in err and "empty" in err and "{}" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ extends


def test_extends_deep_merges_relative_to_the_file(tmp_path, monkeypatch):
    """A child overrides single keys of its parent's sections, replaces lists, and finds the
    parent relative to itself (not the working directory); `--set` comes last.

    Catches: a shallow merge (a child's `grasping: {f_d}` wiping the parent's other grasping
    keys), a path resolved against the cwd, overrides applied before extends."""
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "parent.yaml").write_text(
        "grasping: {f_d: 2.0, k_pg: 0.2}\nqp:\n  limits: [{type: joint_position}, {type: joint_velocity}]\n")
    (tmp_path / "child").mkdir()
    child = tmp_path / "child" / "child.yaml"
    child.write_text("extends: ../base/parent.yaml\ngrasping: {f_d: 2.5}\nqp:\n  limits: [{type: joint_position}]\n")
    monkeypatch.chdir(tmp_path / "base")
    settings = load_settings(child, ["grasping.k_og=0.7"])
    assert settings.grasping.f_d == 2.5  # the child's
    assert settings.grasping.k_pg == 0.2  # the parent's, kept by the deep merge
    assert settings.grasping.k_og == 0.7  # --set
    assert settings.grasping.k_fp == 0.001  # the default
    assert [e.type for e in settings.qp.limits] == ["joint_position"]  # lists are replaced


def test_extends_cycles_and_missing_parents_are_clear_errors(tmp_path):
    """Catches: infinite recursion on a cycle, or a KeyError/RecursionError instead of a ConfigError."""
    (tmp_path / "a.yaml").write_text("extends: b.yaml\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\n")
    with pytest.raises(ConfigError, match=r"'extends' makes a cycle .*a\.yaml -> .*b\.yaml -> .*a\.yaml"):
        load_config(tmp_path / "a.yaml")
    (tmp_path / "self.yaml").write_text("extends: self.yaml\n")
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "self.yaml")
    (tmp_path / "orphan.yaml").write_text("extends: gone.yaml\n")
    with pytest.raises(ConfigError, match=r"orphan\.yaml: 'extends' names 'gone.yaml'"):
        load_config(tmp_path / "orphan.yaml")
    (tmp_path / "diamond.yaml").write_text("extends: [left.yaml, right.yaml]\n")
    (tmp_path / "left.yaml").write_text("extends: root.yaml\ngrasping: {f_d: 2.0}\n")
    (tmp_path / "right.yaml").write_text("extends: root.yaml\n")
    (tmp_path / "root.yaml").write_text("grasping: {f_d: 1.0, k_pg: 0.3}\n")
    merged = load_config(tmp_path / "diamond.yaml")  # a diamond is not a cycle
    assert merged.grasping.k_pg == 0.3


def test_an_error_names_the_file_of_the_extends_chain_that_holds_the_bad_key(tmp_path):
    """Catches: blaming the child for its parent's typo (the user would look in the wrong file)."""
    (tmp_path / "parent.yaml").write_text("reaching: {radius: -1}\n")
    (tmp_path / "child.yaml").write_text("extends: parent.yaml\ngrasping: {f_d: 2.5}\n")
    with pytest.raises(ConfigError) as err:
        load_settings(tmp_path / "child.yaml")
    assert str(err.value).startswith(f"{tmp_path / 'parent.yaml'}: 'reaching.radius' must be a number > 0")
    expected = r"child\.yaml \(--set grasping\.f_d=-2\): 'grasping.f_d' must be a number > 0; got -2"
    with pytest.raises(ConfigError, match=expected):
        load_settings(tmp_path / "child.yaml", ["reaching.radius=0.3", "grasping.f_d=-2"])


def test_the_schema_kinds_share_definitions():
    """One schema: the paper's qp.limits and a task config's limits are the same model."""
    schema = json_schema()
    episode, tasks = schema["$defs"]["EpisodeConfig"], schema["$defs"]["TaskConfig"]
    assert episode["additionalProperties"] is False and tasks["additionalProperties"] is False
    assert schema["$defs"]["QPSection"]["properties"]["limits"]["items"] == tasks["properties"]["limits"]["items"]
    assert set(EpisodeConfig.model_fields) >= {"scene", "camera", "perception", "reaching", "grasping", "qp",
                                                "safety", "episode", "mapper", "obstacle_map"}
    assert {"dt", "tasks", "limits", "solver"} <= set(TaskConfig.model_fields)


def test_the_config_reference_documents_every_key_with_the_default_the_loop_uses():
    """Each key of tasks/paper.yaml has one row in docs/config.md whose default (parsed back from
    the table) equals the value in paper.yaml (whose values equal the defaults), and a unit or a
    description.

    Catches: a flattened section showing its model's own default instead of the enclosing
    default (qp.camera_task.weight is [1, 1, 1, 0.3, 0.3, 0], not 1.0), or a key missing from the docs."""
    rows = {}
    for line in config_reference_markdown().split("## QP task configuration")[0].splitlines():
        if line.startswith("| `"):
            cells = [c.strip() for c in line.strip("|").split(" | ")]
            rows[cells[0].strip("`")] = cells
    raw = yaml.safe_load((tasks_dir() / "paper.yaml").read_text())
    for keys, value in _leaves({k: v for k, v in raw.items() if k != "description"}):
        path = ".".join(keys)
        assert path in rows, path
        key, kind, default, unit, description = rows[path]
        assert description, path
        documented = json.loads(default.strip("`"))
        if path == "qp.limits":  # entries documented with their class defaults spelled out
            documented = [{k: d[k] for k in v} for d, v in zip(documented, value, strict=True)]
        assert documented == value, (path, default, value)


def test_defaults_repeated_from_code_match_the_code():
    """The demo's viewpoint defaults equal `stem_viewpoint`'s own (the demo passes all three).

    Catches: the schema and the function drifting apart (the same file would then mean two things)."""
    import inspect

    from harvest_qp.config.task_schema import Viewpoint
    from harvest_qp.runtime.task_episode import stem_viewpoint

    signature = inspect.signature(stem_viewpoint).parameters
    assert Viewpoint().model_dump() == {k: signature[k].default for k in ("distance", "azimuth", "elevation")}


def test_every_built_in_task_and_limit_type_is_in_the_reference():
    """docs/config.md documents every type the schema accepts. Oracle: the schema's own lists of
    built-in types, not the generator's (a newcomer's new limit type was silently left out of the
    reference because the generator listed the entry classes by hand)."""
    from harvest_qp.config.task_schema import BUILT_IN_LIMITS, BUILT_IN_TASKS

    text = (ROOT / "docs" / "config.md").read_text()
    missing = [kind for kind in (*BUILT_IN_TASKS, *BUILT_IN_LIMITS) if f"### `type: {kind}`" not in text]
    assert missing == []
