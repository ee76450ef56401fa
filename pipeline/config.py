"""Workflows (``workflows/*.toml``) and parameter overrides (``--set stage.param=value``).

Precedence, lowest first: the stage's parameter model defaults, the workflow's tables (and the
workflows it includes), the sequence's ``params`` in ``data/sequences.toml``, then ``--set``.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomllib
from pydantic import ValidationError

from core.errors import UserError
from core.paths import workflows_dir
from core.stage import Stage, StageParams, bool_for_number, flatten_params, nest_params, param_fields

Overrides = dict[str, dict[str, Any]]


def did_you_mean(name: str, options: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(options), n=1, cutoff=0.5)
    return f"; did you mean '{close[0]}'?" if close else ""


@dataclass
class Workflow:
    """A named list of stages with parameter tables."""

    name: str
    stages: list[str]
    params: Overrides = field(default_factory=dict)
    description: str = ""
    sweep: dict[str, list[Any]] = field(default_factory=dict)
    path: Path | None = None


def _load_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: invalid TOML ({exc}); fix the file") from exc


def merge_overrides(*layers: Mapping[str, Mapping[str, Any]]) -> Overrides:
    """Later layers win, parameter by parameter (groups flattened to dotted names, so ``[slam.graph]`` in one
    layer and ``--set slam.graph.loop_radius=...`` in another combine)."""
    out: Overrides = {}
    for layer in layers:
        for stage, values in layer.items():
            out.setdefault(stage, {}).update(flatten_params(values))
    return out


def load_workflow(name_or_path: str, root: Path | None = None, _seen: tuple[str, ...] = ()) -> Workflow:
    """Load ``workflows/<name>.toml`` (or a path), resolving ``include``."""
    root = root or workflows_dir()
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = root / f"{name_or_path}.toml"
    if not path.exists():
        known = sorted(p.stem for p in root.glob("*.toml"))
        raise UserError(
            f"workflow '{name_or_path}' not found ({path}){did_you_mean(str(name_or_path), known)} "
            f"(known: {', '.join(known)})"
        )
    if path.stem in _seen:
        raise UserError(f"{path}: include cycle through {' -> '.join(_seen)}")
    doc = _load_toml(path)
    meta = doc.pop("workflow", {})
    sweep = doc.pop("sweep", {})
    params: Overrides = {}
    for inc in meta.get("include", []):
        params = merge_overrides(params, load_workflow(inc, root, (*_seen, path.stem)).params)
    for stage, table in doc.items():
        if not isinstance(table, dict):
            raise UserError(f"{path}: top-level key '{stage}' must be a table of stage parameters")
    params = merge_overrides(params, doc)
    stages = list(meta.get("stages", []))
    return Workflow(path.stem, stages, params, meta.get("description", ""), dict(sweep), path)


def parse_value(text: str) -> Any:
    """A TOML literal (``5``, ``0.25``, ``true``, ``[1, 2]``, ``"x"``) or else the bare string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_set(items: Iterable[str], registry: Mapping[str, Stage]) -> Overrides:
    """Parse ``stage.param=value`` items; unknown stages or parameters get a did-you-mean error."""
    out: Overrides = {}
    for item in items:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise UserError(f"--set '{item}': expected STAGE.PARAM=VALUE, e.g. --set slam.n_particles=100")
        lhs, raw = item.split("=", 1)
        stage, param = lhs.strip().split(".", 1)
        if stage not in registry:
            raise UserError(f"--set {lhs}: unknown stage '{stage}'{did_you_mean(stage, registry)}")
        check_param_names(stage, {param: raw}, registry, source="--set")
        out.setdefault(stage, {})[param] = parse_value(raw.strip())
    return out


LISTED_PARAMETERS = 12


def parameter_listing(stage: str, names: Sequence[str]) -> str:
    """The stage's parameter names when they fit on a line, else where to read them."""
    if not names:
        return "parameters: none"
    if len(names) <= LISTED_PARAMETERS:
        return f"parameters: {', '.join(names)}"
    return f"{len(names)} parameters: `pipeline params {stage}` lists them with their defaults"


def check_param_names(stage: str, values: Mapping[str, Any], registry: Mapping[str, Stage], source: str) -> None:
    fields = param_fields(registry[stage].Params)
    for param in flatten_params(values):
        if param not in fields:
            in_group = [f for f in fields if f.endswith(f".{param}")]
            close = in_group if len(in_group) == 1 else difflib.get_close_matches(param, list(fields), n=1, cutoff=0.6)
            hint = f"; did you mean '{stage}.{close[0]}'?" if close else ""
            listing = "" if hint else f" ({parameter_listing(stage, list(fields))})"
            raise UserError(f"{source}: unknown parameter '{stage}.{param}'{hint}{listing}")


def build_params(stage: Stage, layers: Sequence[tuple[str, Mapping[str, Any]]]) -> StageParams:
    """Validate the merged parameter layers into the stage's model; errors name the parameter."""
    flat_layers = [(source, flatten_params(values)) for source, values in layers]
    merged: dict[str, Any] = {}
    for _source, values in flat_layers:
        merged.update(values)
    flagged = bool_for_number(param_fields(stage.Params), merged)
    if flagged is not None:
        source = next((s for s, v in reversed(flat_layers) if flagged in v), "defaults")
        raise UserError(f"{source}: {stage.name}.{flagged}={str(merged[flagged]).lower()}: a bool where a number is "
                        f"expected; give a number")
    try:
        return stage.Params.model_validate(nest_params(merged))
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        source = next((s for s, v in reversed(flat_layers) if any(k == loc or k.startswith(f"{loc}.") or
                                                                   loc.startswith(f"{k}.") for k in v)), "defaults")
        value = merged.get(loc, {k: v for k, v in merged.items() if k.startswith(f"{loc}.")} or None)
        raise UserError(f"{source}: {stage.name}.{loc}={value!r}: {err['msg']}") from None


def describe_params(stage: Stage) -> list[tuple[str, str, Any, str]]:
    """(name, type, default, description) for ``pipeline params``."""
    rows = []
    for name, f in param_fields(stage.Params).items():
        ann = getattr(f.annotation, "__name__", str(f.annotation))
        rows.append((name, ann, f.default, f.description or ""))
    return rows


def effective_params(stage: Stage, layers: Sequence[tuple[str, Mapping[str, Any]]]) -> list[tuple[str, Any, str, str]]:
    """(name, value, the layer that set it or ``default``, description) of every parameter, after validating the
    layers as a run does (so an invalid value is the run's error)."""
    params = build_params(stage, layers).model_dump(mode="json")
    flat = flatten_params(params)
    set_by = {k: source for source, values in layers for k in flatten_params(values)}
    return [(name, flat.get(name), set_by.get(name, "default"), info.description or "")
            for name, info in param_fields(stage.Params).items()]
