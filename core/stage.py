"""The stage contract: what a stage declares and what it is handed when it runs.

A stage is a small class in ``stages/<name>/stage.py`` that declares its name, upstream inputs, a typed
parameter model, a code version and the artifacts it writes. Its ``run`` adapts artifacts to the pure
algorithms beside it. The runner owns caching, temporary folders, manifests and locks.
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from pydantic import BaseModel, ConfigDict, model_validator
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from core.errors import UserError

if TYPE_CHECKING:
    from core.recording import StageRecording


#: a report table: (title, headers, rows of cells)
ReportTable = tuple[str, list[str], list[list[str]]]


class StageReport(Protocol):
    """What a stage offers ``pipeline report`` and sweeps: tables and figures over the metric records of many
    runs (``{seq, method, metric, value, section, ...}``, gathered by the orchestration layer).

    ``sequences`` maps each sequence name to ``{"kind", "scene", "split", "environment"}`` (what the registry
    or the run knows), so reports can split map sequences by the paper's test/train split."""

    sweep_figure_kinds: Sequence[str]

    def tables(self, records: Sequence[dict[str, Any]],
               sequences: Mapping[str, Mapping[str, Any]] | None = None) -> list[ReportTable]: ...

    def markdown(self, records: Sequence[dict[str, Any]], title: str,
                 sequences: Mapping[str, Mapping[str, Any]] | None = None) -> str: ...

    def figures(self, records: Sequence[dict[str, Any]], out: Path, curves: Mapping[str, Any],
                runs_dir: Path | None = None) -> list[Path]: ...

    def sweep_tables(self, records: Sequence[dict[str, Any]]) -> list[ReportTable]: ...

    def sweep_figures(self, kind: str, root: Path, name: str, description: str, points: Sequence[Any],
                      seqs: Sequence[str], records: Sequence[Mapping[str, Any]],
                      meta: Mapping[str, Any]) -> list[Path]: ...


def _takes_bool(annotation: Any) -> bool:
    """Whether a field's annotation admits a bool (``bool``, ``bool | None``, ``Literal[True]``...)."""
    import typing

    if annotation is bool:
        return True
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Literal:
        return any(isinstance(a, bool) for a in args)
    return any(_takes_bool(a) for a in args) if args else annotation is Any


def _takes_number(annotation: Any) -> bool:
    import typing

    if annotation in (int, float):
        return True
    return any(_takes_number(a) for a in typing.get_args(annotation))


class StageParams(BaseModel):
    """Base of every stage's parameter model: unknown names are rejected, types are checked, and a bool is
    never taken for a number (``n_particles=true`` is an error, not one particle)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _no_bool_for_numbers(cls, data: Any) -> Any:
        name = bool_for_number(cls, data)
        if name is not None:
            raise ValueError(f"{name}={str(data[name]).lower()}: a bool where a number is expected; give a number")
        return data


def bool_for_number(model: type[BaseModel] | Mapping[str, Any], data: Any) -> str | None:
    """The first field of ``model`` (a model, or ``{name: FieldInfo}``) that ``data`` gives a bool although the
    field takes only numbers."""
    if not isinstance(data, dict):
        return None
    fields = model if isinstance(model, Mapping) else model.model_fields
    for name, value in data.items():
        info = fields.get(name)
        if (isinstance(value, bool) and info is not None and _takes_number(info.annotation)
                and not _takes_bool(info.annotation)):
            return str(name)
    return None


class ParamGroup(StageParams):
    """A nested group of a stage's parameters, addressed with a dot (``slam.graph.loop_radius``, ``[slam.graph]``
    in TOML), as KISS-ICP groups its config."""


def param_fields(model: type[BaseModel], prefix: str = "") -> dict[str, Any]:
    """``{dotted name: FieldInfo}`` of every leaf parameter of ``model``, its groups' included."""
    out: dict[str, Any] = {}
    for name, info in model.model_fields.items():
        group = info.annotation
        if isinstance(group, type) and issubclass(group, ParamGroup):
            out.update(param_fields(group, f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = info
    return out


def flatten_params(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested tables (``{"graph": {"loop_radius": 3}}``) as dotted names (``{"graph.loop_radius": 3}``), so that
    layers merge name by name. No stage parameter takes a table, so every mapping is a group."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out.update(flatten_params(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def nest_params(flat: Mapping[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`flatten_params`: dotted names as nested tables, for ``model_validate``."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        *groups, leaf = key.split(".")
        node = out
        for g in groups:
            node = node.setdefault(g, {})
        node[leaf] = value
    return out


class Stage(ABC):
    """One cached step of the pipeline."""

    name: ClassVar[str]
    description: ClassVar[str] = ""
    #: upstream stages whose artifacts this stage reads
    inputs: ClassVar[tuple[str, ...]] = ()
    #: upstream stages read when available (installed and implemented); part of the key when present
    optional_inputs: ClassVar[tuple[str, ...]] = ()
    Params: ClassVar[type[StageParams]] = StageParams
    #: bump when the stage's outputs change meaning; the package source digest is added automatically
    version: ClassVar[str] = "1"
    #: artifact files the stage must write (the runner checks them)
    outputs: ClassVar[tuple[str, ...]] = ()
    #: importable modules the stage needs (an optional extra), with the extra's name for the message
    requires: ClassVar[tuple[str, ...]] = ()
    requires_extra: ClassVar[str] = ""
    implemented: ClassVar[bool] = True
    #: what the sequence's source must provide (``sources.PROVIDES``: ``log`` = sensor streams, ``maps`` =
    #: published voxel maps); the runner skips the stage, and everything that needs it, when it does not
    needs: ClassVar[frozenset[str]] = frozenset()

    def skip_reason(self, seq: Any, params: StageParams) -> str | None:
        """Why this stage cannot run for ``seq`` at all (one line), or None. Known before anything runs
        (the source kind, the parameters); the default checks :attr:`needs` against the source."""
        missing = sorted(self.needs - seq.provides)
        if missing:
            return f"'{seq.name}' is a {seq.kind_label}, it has no {' or '.join(missing)}"
        return None

    def skip_reason_for_inputs(self, seq: Any, params: StageParams,
                               input_dirs: Mapping[str, Path]) -> str | None:
        """Why this stage cannot run on what its inputs hold (one line, e.g. "the log has no lidar"), or
        None. Called once every input is finished, before the stage would run or be taken from the cache."""
        return None

    def input_stages(self, params: StageParams) -> tuple[str, ...]:
        """Upstream stages for these parameters (override when a parameter picks an input)."""
        return self.inputs

    def optional_input_stages(self, params: StageParams) -> tuple[str, ...]:
        """Stages used when they can run for the sequence, for these parameters."""
        return self.optional_inputs

    def key_material(self, seq: Any, params: StageParams) -> dict[str, Any]:
        """Extra values that enter the cache key (e.g. the fingerprint of a source bag)."""
        return {}

    def memory_estimate(self, seq: Any, params: StageParams,
                        input_dirs: Mapping[str, Path]) -> tuple[int, str] | None:
        """Peak bytes the stage will hold for these parameters and finished inputs, with the parameters that set
        it (``"slam.n_particles=200 x slam.map.n_basis=256^2"``); None when it is small or not modelled. The runner
        refuses a run whose estimate exceeds the memory available, before it starts."""
        return None

    def report(self) -> StageReport | None:
        """Tables and figures over many runs of this stage (``pipeline report``); None when it has none."""
        return None

    def missing_requirements(self) -> list[str]:
        return [m for m in self.requires if importlib.util.find_spec(m) is None]

    def unavailable_reason(self) -> str | None:
        if not self.implemented:
            return "not implemented yet"
        missing = self.missing_requirements()
        if missing:
            extra = (f" (the '{self.requires_extra}' extra: pip install -e '.[{self.requires_extra}]', or make demo)"
                     if self.requires_extra else "")
            return f"needs {', '.join(missing)}, not installed{extra}"
        return None

    def code_version(self) -> str:
        """Declared version plus a digest of the stage package's source files."""
        return f"{self.version}+{source_digest(type(self))}"

    @abstractmethod
    def run(self, ctx: StageContext) -> None:
        """Read inputs from ``ctx``, compute, write artifacts into ``ctx.out_dir``."""


@cache
def source_digest(cls: type) -> str:
    """Short sha256 over the stage's source: its package's ``.py`` files (``stages/<name>/``) when it is
    defined in a ``stage.py``, else just its module file."""
    module_file = inspect.getsourcefile(cls)
    if module_file is None:
        return "unknown"
    path = Path(module_file)
    files = sorted(path.parent.glob("*.py")) if path.name == "stage.py" else [path]
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


@dataclass
class StageContext:
    """Everything a running stage may touch."""

    stage: str
    seq: Any  # the sequence record, sources.sequence.SequenceInfo (core stands below sources)
    params: Any
    out_dir: Path
    input_dirs: dict[str, Path]
    console: Console
    #: values recorded in the manifest (counts of dropped points, warnings, measured numbers)
    stats: dict[str, Any] = field(default_factory=dict)
    _recording: StageRecording | None = None

    def input(self, stage: str, filename: str) -> Path:
        """Path of an upstream artifact; a clear error when it is absent."""
        if stage not in self.input_dirs:
            raise UserError(
                f"stage '{self.stage}' read '{stage}/{filename}' but '{stage}' is not among its inputs"
            )
        path = self.input_dirs[stage] / filename
        if not path.exists():
            raise UserError(f"{path}: missing; run `pipeline run {stage} --seq {self.seq.name} --force`")
        return path

    def has_input(self, stage: str) -> bool:
        return stage in self.input_dirs

    def output(self, filename: str) -> Path:
        return self.out_dir / filename

    @property
    def recording(self) -> StageRecording:
        """The stage's Rerun recording (``<stage>.rrd`` in the output folder), opened on first use."""
        if self._recording is None:
            from core.recording import StageRecording

            self._recording = StageRecording(self.seq.name, self.out_dir / f"{self.stage}.rrd")
        return self._recording

    def close(self) -> None:
        """Write the recording out (a write error, e.g. a full disk, is raised)."""
        if self._recording is not None:
            rec, self._recording = self._recording, None
            rec.close()

    def abort(self) -> None:
        """Release the recording without writing it (the stage failed; its folder is removed)."""
        if self._recording is not None:
            rec, self._recording = self._recording, None
            rec.abort()

    def warn(self, message: str) -> None:
        """Print a warning and keep it in the manifest."""
        self.console.print(f"[yellow]warning[/] {self.stage}: {escape(message)}")
        self.stats.setdefault("warnings", []).append(message)

    #: seconds between the plain progress lines printed when the console is not a terminal (a log, CI, ``tee``)
    PLAIN_PROGRESS_EVERY_S: ClassVar[float] = 30.0

    @contextmanager
    def progress(self, total: int | None, description: str) -> Iterator[Any]:
        """A rich progress bar on a terminal, otherwise a plain line every ``PLAIN_PROGRESS_EVERY_S`` seconds;
        yields ``advance(n=1)``."""
        import time

        plain = not self.console.is_terminal
        start = last = time.monotonic()
        done = 0
        with Progress(
            TextColumn(f"[bold blue]{self.stage}[/] {description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=self.console,
            transient=True,
            disable=not self.console.is_terminal,
        ) as prog:
            task = prog.add_task(description, total=total)

            def advance(n: int = 1) -> None:
                nonlocal done, last
                prog.advance(task, n)
                done += n
                now = time.monotonic()
                if plain and now - last >= self.PLAIN_PROGRESS_EVERY_S:
                    last = now
                    share = f" ({100 * done / total:.0f} %)" if total else ""
                    self.console.print(f"{self.stage} {escape(description)}: {done}/{total or '?'}{share}, "
                                       f"{now - start:.0f} s", highlight=False)

            yield advance


def parquet_rows(path: Path) -> int | None:
    """Row count of a Parquet file from its footer (cheap), or None when it is absent or unreadable."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return int(pq.ParquetFile(path).metadata.num_rows)
    except (OSError, pa.ArrowInvalid):
        return None


def blas_threads(n: int) -> AbstractContextManager[Any]:
    """Limit the BLAS thread pools to ``n`` threads (``threadpoolctl``) for the duration; 0 leaves them.

    Small dense problems (planning, GP fits) run faster single-threaded, most of all on a shared machine.
    """
    if n <= 0:
        return nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a dependency, but never fatal
        return nullcontext()
    return threadpool_limits(n, user_api="blas")
