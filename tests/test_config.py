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
    n = len(reg["slam"].Params.model_fields)
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


# Where the default workflow may differ from a stage's own defaults, and why. Everything else it states must be
# the stage's default: the tables (experiments.slam_table3, benchmarks) run the stage defaults, and `pipeline run all`
# must run what they measured.
INTENDED_WORKFLOW_DIFFERENCES: dict[tuple[str, str], str] = {}


def test_the_default_workflow_runs_the_stage_defaults() -> None:
    from pipeline.registry import load_stages

    registry = load_stages()
    workflow = load_workflow("default")
    differences = []
    for stage, values in workflow.params.items():
        defaults = registry[stage].Params().model_dump()
        for name, value in values.items():
            if (stage, name) not in INTENDED_WORKFLOW_DIFFERENCES and defaults[name] != value:
                differences.append(f"{stage}.{name}: workflow {value!r}, stage default {defaults[name]!r}")
    assert differences == []
    for stage, name in INTENDED_WORKFLOW_DIFFERENCES:  # each exception is still one (else drop it from the list)
        assert workflow.params[stage][name] != registry[stage].Params().model_dump()[name]
