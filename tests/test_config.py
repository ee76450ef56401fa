"""Workflows, includes, parameter precedence and --set parsing."""

from __future__ import annotations

from pathlib import Path

import pytest

from core.errors import UserError
from pipeline.config import load_workflow, parse_set, parse_value
from pipeline.runner import Runner
from pipeline.sequences import SequenceInfo
from tests import toy_stages


def test_parse_value_types() -> None:
    assert parse_value("5") == 5
    assert parse_value("0.25") == 0.25
    assert parse_value("true") is True
    assert parse_value("[1, 2]") == [1, 2]
    assert parse_value("groundtruth") == "groundtruth"
    assert parse_value('"quoted"') == "quoted"


def test_parse_set_errors() -> None:
    reg = toy_stages.registry()
    assert parse_set(["square.offset=2.5"], reg) == {"square": {"offset": 2.5}}
    with pytest.raises(UserError, match=r"expected STAGE.PARAM=VALUE"):
        parse_set(["offset=2"], reg)
    with pytest.raises(UserError, match=r"unknown stage 'squar'; did you mean 'square'\?"):
        parse_set(["squar.offset=2"], reg)
    with pytest.raises(UserError, match=r"unknown parameter 'square.offsett'; did you mean 'square.offset'\?"):
        parse_set(["square.offsett=2"], reg)
    with pytest.raises(UserError, match=r"unknown parameter 'square.zzz' \(parameters: offset, fail_midway, "):
        parse_set(["square.zzz=2"], reg)


def test_a_long_parameter_list_points_to_the_params_command() -> None:
    from pipeline.config import LISTED_PARAMETERS
    from pipeline.registry import load_stages

    reg = load_stages()
    from core.stage import param_fields

    n = len(param_fields(reg["slam"].Params))
    assert n > LISTED_PARAMETERS
    with pytest.raises(UserError) as err:
        parse_set(["slam.qqqqqqqq=2"], reg)
    message = str(err.value)
    assert message == (f"--set: unknown parameter 'slam.qqqqqqqq' ({n} parameters: "
                       "`pipeline params slam` lists them with their defaults)")


def test_type_errors_name_the_parameter_and_source(tmp_path: Path) -> None:
    reg = toy_stages.registry()
    seq = SequenceInfo(name="s", kind="source", source=tmp_path)
    runner = Runner(seq, tmp_path, reg, toy_stages.workflow(), parse_set(["make_numbers.count=abc"], reg))
    with pytest.raises(UserError, match=r"--set: make_numbers.count='abc': Input should be a valid integer"):
        runner.params("make_numbers")


def test_precedence_defaults_workflow_sequence_set(tmp_path: Path) -> None:
    reg = toy_stages.registry()
    seq = SequenceInfo(name="s", kind="source", source=tmp_path, params={"make_numbers": {"count": 7, "scale": 3.0}})
    wf = toy_stages.workflow(make_numbers={"count": 4, "scale": 2.0}, square={"offset": 9.0})
    runner = Runner(seq, tmp_path, reg, wf, {"make_numbers": {"scale": 5.0}})
    p = runner.params("make_numbers")
    assert (p.count, p.scale) == (7, 5.0)  # sequence beats workflow, --set beats sequence
    assert runner.params("square").offset == 9.0


def test_workflow_include_and_missing(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text('[square]\noffset = 1.0\n[make_numbers]\ncount = 2\n')
    (tmp_path / "main.toml").write_text(
        '[workflow]\nstages = ["make_numbers", "square"]\ninclude = ["base"]\n[square]\noffset = 4.0\n'
    )
    wf = load_workflow("main", root=tmp_path)
    assert wf.stages == ["make_numbers", "square"]
    assert wf.params == {"square": {"offset": 4.0}, "make_numbers": {"count": 2}}
    with pytest.raises(UserError, match=r"workflow 'mian' not found .*did you mean 'main'\?"):
        load_workflow("mian", root=tmp_path)
    (tmp_path / "bad.toml").write_text("[workflow\n")
    with pytest.raises(UserError, match=r"bad.toml: invalid TOML"):
        load_workflow("bad", root=tmp_path)


def test_shipped_workflows_load_and_name_real_parameters() -> None:
    from pipeline.registry import load_stages

    reg = load_stages()
    for name in ("default", "rich_slam", "rmap"):
        wf = load_workflow(name)
        assert set(wf.stages) <= set(reg)
        Runner(SequenceInfo(name="demo", kind="simulated", world="demo"), Path("/tmp/unused"), reg, wf)


def test_workflows_state_only_what_differs_from_the_stage_defaults() -> None:
    """A workflow that repeats a default hides where the value is set (and goes stale when the default moves)."""
    import tomllib

    from core.paths import workflows_dir
    from core.stage import flatten_params
    from pipeline.registry import load_stages

    registry = load_stages()
    repeated = []
    for path in sorted(workflows_dir().glob("*.toml")):
        doc = tomllib.loads(path.read_text())
        for stage, values in doc.items():
            if stage in ("workflow", "sweep"):
                continue
            defaults = flatten_params(registry[stage].Params().model_dump(mode="json"))
            repeated += [f"{path.name}: {stage}.{k} = {v!r}" for k, v in flatten_params(values).items()
                         if defaults.get(k) == v]
    assert repeated == []


def test_nested_groups_from_toml_set_and_layers(tmp_path: Path) -> None:
    """``[slam.graph]`` in a workflow and ``--set slam.graph.x=...`` combine name by name; a bare group member
    is pointed to its group; a bool is not taken for a number inside a group either."""
    from pipeline.config import build_params, effective_params, merge_overrides
    from pipeline.registry import load_stages

    reg = load_stages()
    wf = tmp_path / "g.toml"
    wf.write_text('[workflow]\nstages = ["slam"]\n[slam.graph]\nloop_radius = 4.0\nbias_walk = 0.001\n')
    layers = [("workflow g", load_workflow(str(wf)).params["slam"]),
              ("--set", parse_set(["slam.graph.loop_radius=5.0"], reg)["slam"])]
    p = build_params(reg["slam"], layers)
    assert p.graph.loop_radius == 5.0 and p.graph.bias_walk == 0.001  # type: ignore[attr-defined]
    assert merge_overrides({"slam": {"graph": {"a": 1}}}, {"slam": {"graph.b": 2}}) == {"slam": {"graph.a": 1,
                                                                                              "graph.b": 2}}
    set_by = {name: layer for name, _v, layer, _d in effective_params(reg["slam"], layers)}
    assert set_by["graph.loop_radius"] == "--set" and set_by["graph.bias_walk"] == "workflow g"
    assert set_by["n_particles"] == "default"
    with pytest.raises(UserError, match=r"did you mean 'slam\.graph\.loop_radius'"):
        parse_set(["slam.loop_radius=3"], reg)
    with pytest.raises(UserError, match=r"slam\.map\.n_basis=true: a bool"):
        build_params(reg["slam"], [("--set", {"map.n_basis": True})])
    with pytest.raises(UserError, match=r"--set: slam\.map\.n_basis=250: .*perfect square"):
        build_params(reg["slam"], [("--set", {"map.n_basis": 250})])


def test_slam_exposes_at_most_thirty_one_parameters_in_groups() -> None:
    """A guard against options piling up again: what the papers fix is a constant beside its algorithm."""
    from core.stage import param_fields
    from pipeline.registry import load_stages

    names = list(param_fields(load_stages()["slam"].Params))
    assert len(names) <= 31, names
    assert {n.split(".")[0] for n in names if "." in n} == {"map", "beams", "graph", "grid"}
