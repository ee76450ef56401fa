"""Resolving the stage DAG, computing keys, skipping cached stages and running the rest.

Stages that cannot run for a sequence are *skipped*, with a one-line reason, together with every stage
that needs them (an optional input that is skipped is just left out): statically when the source does not
provide what the stage needs or its parameters rule it out (:meth:`Stage.skip_reason`, e.g. a map
sequence has no log to ingest), or once its inputs are finished when they lack something
(:meth:`Stage.skip_reason_for_inputs`, e.g. a radar + IMU log has no ground truth). ``run all`` then ends
normally (exit 0); a stage named explicitly that cannot run is a user error.

A stage that cannot run on this installation (:meth:`Stage.unavailable_reason`: a missing extra, e.g.
``complete`` without torch) is different: the sequence would use it. A named target that needs it, also as
an optional input (``evaluate`` uses ``complete``), is refused with a one-line user error that names it,
the reason and the install command, before anything runs; ``run all`` goes on without it, with a skip row
in the stage table and a warning on stderr for every stage that ran without it.
"""

from __future__ import annotations

import graphlib
import json
import platform
import shutil
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import cached_property
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from core.errors import UserError
from core.stage import Stage, StageContext, StageParams, flatten_params
from pipeline import __version__
from pipeline.config import Overrides, Workflow, build_params, check_param_names
from pipeline.resources import available_memory, folder_size, free_space, human_bytes, is_disk_full
from pipeline.sequences import SequenceInfo
from pipeline.store import RunStore, compute_key
from schemas.io import SchemaError


@dataclass
class StageStatus:
    stage: str
    state: str  # done | stale | damaged | missing | unavailable
    reason: str = ""
    key: str | None = None
    seconds: float | None = None
    finished_at: str | None = None


@dataclass
class StageOutcome:
    stage: str
    action: str  # ran | cached | reused | skipped | failed
    seconds: float = 0.0
    reason: str = ""
    error: BaseException | None = field(default=None, repr=False, compare=False)


class StagesFailed(Exception):
    """One or more stages failed; ``outcomes`` has every stage's result, ``first`` the first error."""

    def __init__(self, outcomes: list[StageOutcome], first: BaseException) -> None:
        names = [o.stage for o in outcomes if o.action == "failed"]
        more = f" (and {', '.join(names[1:])})" if names[1:] else ""
        super().__init__(f"stage '{names[0]}' failed: {first}{more}")
        self.outcomes = outcomes
        self.first = first

    @property
    def user_error(self) -> bool:
        """All failures are user errors (exit code 2) rather than bugs (exit code 1)."""
        return all(isinstance(o.error, UserError) for o in self.outcomes if o.error is not None)


class Runner:
    """Runs stages of one sequence against one run store."""

    def __init__(
        self,
        seq: SequenceInfo,
        runs_dir: Path,
        registry: Mapping[str, Stage],
        workflow: Workflow,
        overrides: Overrides | None = None,
        console: Console | None = None,
        reuse_from: Iterable[Path] = (),
    ) -> None:
        self.seq = seq
        self.registry = dict(registry)
        self.workflow = workflow
        self.overrides = overrides or {}
        self.console = console or Console(stderr=True)
        self.store = RunStore(Path(runs_dir), seq.name)
        #: other run stores whose finished stages with the same key are reused instead of recomputed
        self.reuse = [RunStore(Path(d), seq.name) for d in reuse_from if Path(d).resolve() != Path(runs_dir).resolve()]
        self._params: dict[str, StageParams] = {}
        self._keys: dict[str, str] = {}
        #: stage -> (reason, the stage whose reason it is) for stages known to be skipped
        self._skips: dict[str, tuple[str, str] | None] = {}
        self._data_skips: dict[str, tuple[str, str]] = {}
        self._explicit: list[str] = []
        self._check_names()

    @cached_property
    def kind_params(self) -> Overrides:
        """Parameters every sequence of this source kind starts from (``data/kinds.toml``, read once per runner),
        for the stages of this registry."""
        from pipeline.sequences import kind_defaults

        return {k: v for k, v in kind_defaults(self.seq.kind).items() if k in self.registry}

    def _check_names(self) -> None:
        for source, layer in (
            (f"workflow {self.workflow.path or self.workflow.name}", self.workflow.params),
            (f"defaults of {self.seq.kind} sequences", self.kind_params),
            (f"sequence '{self.seq.name}' params", self.seq.params),
            ("--set", self.overrides),
        ):
            for stage, values in layer.items():
                if stage not in self.registry:
                    from pipeline.config import did_you_mean

                    raise UserError(f"{source}: unknown stage '{stage}'{did_you_mean(stage, self.registry)}")
                check_param_names(stage, values, self.registry, source)
        for stage in self.workflow.stages:
            if stage not in self.registry:
                raise UserError(f"workflow '{self.workflow.name}': unknown stage '{stage}'")

    # -- parameters and keys ------------------------------------------------------------------------------
    def param_layers(self, name: str) -> list[tuple[str, Mapping[str, Any]]]:
        """Stage ``name``'s parameter layers above its defaults, later ones winning: the workflow, the sequence
        kind (``data/kinds.toml``), the sequence (``data/sequences.toml``), ``--set``."""
        return [
            (f"workflow '{self.workflow.name}'", self.workflow.params.get(name, {})),
            (f"{self.seq.kind} sequences", self.kind_params.get(name, {})),
            (f"sequence '{self.seq.name}'", self.seq.params.get(name, {})),
            ("--set", self.overrides.get(name, {})),
        ]

    def params(self, name: str) -> StageParams:
        if name not in self._params:
            self._params[name] = build_params(self.registry[name], self.param_layers(name))
        return self._params[name]

    def inputs_of(self, name: str) -> list[str]:
        stage = self.registry[name]
        params = self.params(name)
        required = list(stage.input_stages(params))
        optional = [s for s in stage.optional_input_stages(params) if s in self.registry and self.available(s)
                    and s not in required and self.skipped(s) is None]
        return required + optional

    # -- skipping -------------------------------------------------------------------------------------------
    def skipped(self, name: str, _stack: tuple[str, ...] = ()) -> tuple[str, str] | None:
        """(reason, origin stage) when ``name`` cannot run for this sequence (known so far), else None."""
        if name in self._data_skips:
            return self._data_skips[name]
        if name in self._skips:
            return self._skips[name]
        if name in _stack:
            raise RuntimeError(f"stage dependency cycle: {' -> '.join((*_stack, name))}")
        stage = self.registry[name]
        own = stage.skip_reason(self.seq, self.params(name))
        out: tuple[str, str] | None = (own, name) if own else None
        if out is None:
            for dep in stage.input_stages(self.params(name)):
                up = self.skipped(dep, (*_stack, name)) if dep in self.registry else None
                if up is not None:
                    out = up
                    break
        self._skips[name] = out
        return out

    def skip_message(self, name: str) -> str:
        """The one-line reason printed for a skipped stage."""
        found = self.skipped(name)
        if found is None:
            return ""
        reason, origin = found
        return reason if origin == name else f"needs '{origin}', skipped: {reason}"

    def _skip_for_inputs(self, name: str) -> str | None:
        """Ask the stage, once its inputs are finished, whether it can run on them; remember a skip."""
        stage = self.registry[name]
        dirs = {i: self.store.stage_dir(i) for i in self.inputs_of(name)}
        reason = stage.skip_reason_for_inputs(self.seq, self.params(name), dirs)
        if reason:
            self._data_skips[name] = (reason, name)
            self._skips.clear()  # downstream skips and optional inputs change with it
            self._keys.clear()
        return reason

    def available(self, name: str) -> bool:
        return self.registry[name].unavailable_reason() is None

    def left_out(self, plan: Iterable[str]) -> list[tuple[str, str, str]]:
        """(stage, optional input, reason) for every optional input that a stage of ``plan`` would use for this
        sequence (it is not skipped for it) but that cannot run on this installation."""
        out = []
        for name in plan:
            for dep in self.registry[name].optional_input_stages(self.params(name)):
                if dep not in self.registry or self.available(dep) or self.skipped(dep) is not None:
                    continue
                out.append((name, dep, self.registry[dep].unavailable_reason() or "unavailable"))
        return out

    def key(self, name: str, _stack: tuple[str, ...] = ()) -> str:
        if name in _stack:
            raise RuntimeError(f"stage dependency cycle: {' -> '.join((*_stack, name))}")
        if name not in self._keys:
            stage = self.registry[name]
            inputs = {i: self.key(i, (*_stack, name)) for i in self.inputs_of(name)}
            self._keys[name] = compute_key(
                name,
                self.params(name).model_dump(mode="json"),
                stage.code_version(),
                inputs,
                stage.key_material(self.seq, self.params(name)),
            )
        return self._keys[name]

    def closure(self, targets: Iterable[str]) -> list[str]:
        """Targets and all their upstream stages, in dependency order."""
        graph: dict[str, set[str]] = {}
        todo = list(targets)
        while todo:
            name = todo.pop()
            if name in graph:
                continue
            if name not in self.registry:
                from pipeline.config import did_you_mean

                raise UserError(f"unknown stage '{name}'{did_you_mean(name, self.registry)}")
            deps = set(self.inputs_of(name))
            graph[name] = deps
            todo.extend(deps)
        order = list(self.registry)
        ts = graphlib.TopologicalSorter(graph)
        ts.prepare()
        out: list[str] = []
        while ts.is_active():
            ready = sorted(ts.get_ready(), key=order.index)
            out.extend(ready)
            ts.done(*ready)
        return out

    # -- status -----------------------------------------------------------------------------------------------
    def stage_status(self, name: str) -> StageStatus:
        reason = self.registry[name].unavailable_reason()
        if reason:
            return StageStatus(name, "unavailable", reason)
        if self.skipped(name) is not None:
            return StageStatus(name, "unavailable", self.skip_message(name))
        for dep in self.inputs_of(name):
            dep_reason = self.registry[dep].unavailable_reason()
            if dep_reason:
                return StageStatus(name, "unavailable", f"input '{dep}' {dep_reason}")
        key = self.key(name)
        manifest = self.store.read_manifest(name)
        if manifest is None:
            return StageStatus(name, "missing", "never run" if not self.store.stage_dir(name).exists()
                               else "incomplete result", key)
        timing = manifest.get("timings", {})
        damage = self.store.damage(name, manifest=manifest)
        if damage is not None:
            return StageStatus(name, "damaged", damage, key, timing.get("seconds"), timing.get("finished_at"))
        if manifest.get("key") == key:
            return StageStatus(name, "done", "", key, timing.get("seconds"), timing.get("finished_at"))
        return StageStatus(name, "stale", self._why_stale(name, manifest), key,
                           timing.get("seconds"), timing.get("finished_at"))

    def _why_stale(self, name: str, manifest: dict[str, Any]) -> str:
        reasons = []
        now = flatten_params(self.params(name).model_dump(mode="json"))  # group members named one by one
        before = flatten_params(manifest.get("params", {}))
        changed = [f"{k} {before.get(k)!r}->{now.get(k)!r}" for k in sorted(set(now) | set(before))
                   if json.dumps(now.get(k), sort_keys=True) != json.dumps(before.get(k), sort_keys=True)]
        if changed:
            reasons.append("params changed: " + ", ".join(changed))
        if manifest.get("code_version") != self.registry[name].code_version():
            reasons.append("code changed")
        old_inputs = manifest.get("inputs", {})
        for dep in self.inputs_of(name):
            if old_inputs.get(dep) != self.key(dep):
                reasons.append(f"input '{dep}' changed")
        for dep in set(old_inputs) - set(self.inputs_of(name)):
            reasons.append(f"input '{dep}' no longer used")
        if manifest.get("extra") != self.registry[name].key_material(self.seq, self.params(name)):
            reasons.append("source data changed")
        return "; ".join(reasons) or "key changed"

    def status(self, stages: Iterable[str] | None = None) -> list[StageStatus]:
        return [self.stage_status(n) for n in (stages or self.registry)]

    # -- running ----------------------------------------------------------------------------------------------
    def resolve_targets(self, targets: Iterable[str]) -> tuple[list[str], list[StageOutcome]]:
        """Expand ``all`` into the workflow's stages that can run; refuse named stages that cannot."""
        targets = list(targets)
        skipped: list[StageOutcome] = []
        out: list[str] = []
        for t in targets:
            if t == "all":
                for s in self.workflow.stages:
                    reason = self.registry[s].unavailable_reason()
                    blocked = [d for d in self.registry[s].input_stages(self.params(s)) if not self.available(d)]
                    if reason or blocked:
                        skipped.append(StageOutcome(s, "skipped", reason=reason or f"input '{blocked[0]}' unavailable"))
                    elif self.skipped(s) is not None:
                        skipped.append(StageOutcome(s, "skipped", reason=self.skip_message(s)))
                    else:
                        out.append(s)
                continue
            if t not in self.registry:
                from pipeline.config import did_you_mean

                raise UserError(f"unknown stage '{t}'{did_you_mean(t, [*self.registry, 'all'])}")
            if self.skipped(t) is not None:
                raise UserError(f"stage '{t}' cannot run for sequence '{self.seq.name}': {self.skip_message(t)}")
            out.append(t)
        for name in self.closure(out):
            reason = self.registry[name].unavailable_reason()
            if reason:
                raise UserError(f"stage '{name}' cannot run: {reason}")
        self._explicit = [t for t in targets if t != "all"]
        needed = self.left_out(self.closure(self._explicit)) if self._explicit else []
        if needed:
            stage, dep, reason = needed[0]
            raise UserError(f"stage '{stage}' needs '{dep}' for sequence '{self.seq.name}', and '{dep}' cannot run: "
                            f"{reason}; `pipeline run all` goes on without it")
        for _stage, dep, reason in self.left_out(self.closure(out)):
            if not any(o.stage == dep for o in skipped):
                skipped.append(StageOutcome(dep, "skipped", reason=reason))
        return list(dict.fromkeys(out)), skipped

    def run(self, targets: Iterable[str], force: Iterable[str] = (), keep_going: bool = True) -> list[StageOutcome]:
        """Bring ``targets`` up to date: run missing or stale stages (and upstream), skip cached ones.

        With ``keep_going`` a failing stage does not stop stages that do not depend on it; when any stage
        failed, :class:`StagesFailed` is raised at the end carrying every outcome.
        """
        wanted, outcomes = self.resolve_targets(targets)
        for o in outcomes:
            self.console.print(f"[yellow]{o.stage:<9} skipped[/]: {escape(o.reason)}")
        force = set(force)
        if "all" in force:
            force = set(wanted)
        plan = self.closure(wanted)
        with self.store.lock():
            for note in self.store.recover():
                self.console.print(f"[yellow]note[/] {self.seq.name}: {escape(note)}")
            failed: list[StageOutcome] = []
            for name in plan:
                blocked = [d for d in self.inputs_of(name) if any(f.stage == d for f in failed)]
                if blocked:
                    skip = StageOutcome(name, "skipped", reason=f"input '{blocked[0]}' failed")
                    outcomes.append(skip)
                    failed.append(skip)
                    continue
                if self.skipped(name) is not None or self._skip_for_inputs(name):
                    skip = StageOutcome(name, "skipped", reason=self.skip_message(name))
                    outcomes.append(skip)
                    self.console.print(f"[yellow]{name:<9} skipped[/]: {escape(skip.reason)}")
                    continue
                st = self.stage_status(name)
                if st.state == "done" and name not in force:
                    damage = self.store.damage(name, checksums=True)
                    if damage is None:
                        outcomes.append(StageOutcome(name, "cached", st.seconds or 0.0))
                        self.console.print(f"[dim]{name:<9} cached[/]")
                        continue
                    st = StageStatus(name, "damaged", damage, st.key)
                    self.console.print(f"[yellow]warning[/] {self.seq.name}: the cached '{name}' result is damaged "
                                       f"({escape(damage)}); running it again", soft_wrap=True)
                if name not in force and self._reuse(name):
                    outcomes.append(StageOutcome(name, "reused", 0.0))
                    self.console.print(f"[dim]{name:<9} reused[/]")
                    continue
                why = "forced" if name in force else (st.reason if st.state == "stale" else st.state)
                if st.state == "damaged":
                    why = "damaged result"
                self.console.print(f"[bold]{name:<9}[/] running ({why})")
                before = self.store.read_manifest(name) if st.state == "stale" else None
                if before is not None and before.get("workflow") not in (None, self.workflow.name):
                    self.console.print(f"[yellow]note[/] {self.seq.name}: this replaces the '{name}' result made with "
                                       f"workflow '{escape(str(before['workflow']))}' (a run folder keeps one result "
                                       f"per stage; pass another --runs-dir to keep both)", soft_wrap=True)
                try:
                    seconds = self._execute(name)
                except Exception as exc:
                    if not keep_going:
                        raise
                    bad = StageOutcome(name, "failed", reason=str(exc).splitlines()[0] if str(exc) else repr(exc),
                                       error=exc)
                    outcomes.append(bad)
                    failed.append(bad)
                    self.console.print(f"[red]{name:<9} failed[/]: {escape(bad.reason)}")
                    continue
                outcomes.append(StageOutcome(name, "ran", seconds, why))
                self.console.print(f"[green]{name:<9} done[/] in {seconds:.1f} s")
        done = {o.stage: o for o in outcomes if o.action in ("ran", "cached", "reused")}
        for stage, dep, reason in self.left_out(plan):
            if stage in done:
                o = done[stage]
                o.reason = "; ".join(x for x in (o.reason, f"without '{dep}' (not installed)") if x)
                self.console.print(f"[yellow]warning[/]: '{stage}' of {self.seq.name} went without '{dep}', which "
                                   f"cannot run: {escape(reason)}")
        errors = [o for o in outcomes if o.error is not None]
        if errors:
            raise StagesFailed(outcomes, errors[0].error)  # type: ignore[arg-type]
        named = [o for o in outcomes if o.action == "skipped" and o.stage in self._explicit]
        if named:
            raise UserError(f"stage '{named[0].stage}' cannot run for sequence '{self.seq.name}': {named[0].reason}")
        return outcomes

    def _reuse(self, name: str) -> bool:
        """Link in a finished result with the same key from another run store, if one exists."""
        key = self.key(name)
        for other in self.reuse:
            manifest = other.read_manifest(name)
            if manifest is not None and manifest.get("key") == key and other.damage(name, checksums=True) is None:
                self.store.import_from(other, name)
                return True
        return False

    def check_memory(self, name: str) -> None:
        """Refuse, before it starts, a stage whose modelled peak memory exceeds what the machine has free."""
        stage = self.registry[name]
        dirs = {i: self.store.stage_dir(i) for i in self.inputs_of(name)}
        estimate = stage.memory_estimate(self.seq, self.params(name), dirs)
        free = available_memory()
        if estimate is None or free is None or estimate[0] <= free:
            return
        need, what = estimate
        raise UserError(f"stage '{name}' of {self.seq.name} would need about {human_bytes(need)} of memory ({what}) "
                        f"and {human_bytes(free)} is available; lower those parameters")

    def _disk_full(self, name: str) -> UserError:
        """The one-line error for a stage that met a full disk (its temporary folder already removed)."""
        free = free_space(self.store.seq_dir) or 0
        before = folder_size(self.store.stage_dir(name))
        took = f"; its last result took {human_bytes(before)}" if before else ""
        return UserError(f"stage '{name}' of {self.seq.name}: the disk is full under {self.store.seq_dir} "
                         f"({human_bytes(free)} free{took}); free space there or pass another --runs-dir; nothing was "
                         f"lost (the previous result is kept)")

    def _execute(self, name: str) -> float:
        stage = self.registry[name]
        params = self.params(name)
        self.check_memory(name)
        try:
            tmp = self.store.new_temp_dir(name)
        except OSError as exc:
            if is_disk_full(exc):
                raise self._disk_full(name) from None
            raise
        ctx = StageContext(
            stage=name,
            seq=self.seq,
            params=params,
            out_dir=tmp,
            input_dirs={i: self.store.stage_dir(i) for i in self.inputs_of(name)},
            console=self.console,
        )
        started = datetime.now(timezone.utc)
        t0 = time.perf_counter()
        try:
            stage.run(ctx)
            ctx.close()
            missing = [o for o in stage.outputs if not (tmp / o).exists()]
            if missing:
                raise RuntimeError(f"stage '{name}' finished without writing {', '.join(missing)}")
            seconds = time.perf_counter() - t0
            manifest = {
                "stage": name,
                "seq": self.seq.name,
                "key": self.key(name),
                "params": params.model_dump(mode="json"),
                "code_version": stage.code_version(),
                "inputs": {i: self.key(i) for i in self.inputs_of(name)},
                "extra": stage.key_material(self.seq, params),
                "timings": {
                    "started_at": started.isoformat(timespec="seconds"),
                    "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "seconds": round(seconds, 3),
                },
                "stats": ctx.stats,
                "pipeline_version": __version__,
                "python": platform.python_version(),
                "workflow": self.workflow.name,
            }
            self.store.commit(name, tmp, manifest)
            return seconds
        except BaseException as exc:
            try:
                ctx.abort()
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(exc, Exception) and is_disk_full(exc):
                raise self._disk_full(name) from None
            if isinstance(exc, SchemaError):  # an input artifact that is not what it should be; the message says so
                raise UserError(str(exc)) from None
            raise
