"""Every command README.md prints keeps working as printed.

The README's fenced ``bash`` blocks are split into commands and each is classified (:func:`classify`):

- ``run``: needs no external data; run, in README order, through ``python -m pipeline`` in a temporary working
  folder with a temporary run store (``./runs``, as printed) and data cache, after ``make demo``'s recipe
  (read from the Makefile). The demo is shortened from 60 s to :data:`DEMO_S` s through a copy of the sequence
  registry (``RADAR_PIPELINE_HOME``), as the README says; everything else is as printed. Exit code 0 expected.
- ``parse``: needs external data (``COLORADAR_ROOT``, a twin's or several map scenes, a log of your own), a
  cluster (Ray), a sweep or a viewer; parsed as the CLI would parse it (options and their types), and every
  ``--set`` names a real parameter with a valid value, every ``--seq`` a registered sequence or glob, every
  ``--workflow`` / sweep / ``--world`` / ``--dataset`` an existing one.
- ``env``: ``export VAR=...`` of a variable the project reads.

Every command is parsed, the runnable ones are also run. A README command this file cannot classify fails
the test: classify it here. Commands on the authors' maps run when the shared maps are beside the clone.
"""

from __future__ import annotations

import glob
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SHARED_MAPS = ROOT.parent / "shared" / "data" / "coloradar_maps"
#: seconds of the demo world the run test simulates (the registry's demo is 60 s: minutes of slam on 2 cores)
DEMO_S = 6.0
#: workflow files a README command names that another change of the same issue adds: skipped until present
PENDING: dict[str, str] = {}  # workflows a README command names before they land: {name: why}
#: subcommands whose runnable forms need nothing but the project itself
LOCAL_SUBCOMMANDS = {"sequences", "params", "profile"}


@dataclass
class Command:
    """One README command: its line, its text, and its argv per ``&&`` part."""

    line: int
    text: str
    parts: list[list[str]]

    @property
    def argv(self) -> list[str]:
        return self.parts[-1]

    def __str__(self) -> str:
        return f"README.md:{self.line}: {self.text}"


@dataclass
class Plan:
    mode: str  # run | parse | env
    reason: str
    needs_shared: bool = False
    env: dict[str, str] = field(default_factory=dict)


def readme_commands(text: str) -> list[Command]:
    """The commands of the fenced ``bash`` blocks (comments and comment lines dropped, ``\\`` lines joined)."""
    out: list[Command] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() != "```bash":
            i += 1
            continue
        i += 1
        pending: tuple[int, str] | None = None
        while i < len(lines) and lines[i].strip() != "```":
            raw = lines[i]
            start, joined = pending if pending else (i + 1, "")
            joined += raw.rstrip().removesuffix("\\") + " "
            pending = (start, joined) if raw.rstrip().endswith("\\") else None
            if pending is None:
                tokens = shlex.split(joined, comments=True)
                if tokens:
                    parts: list[list[str]] = [[]]
                    for tok in tokens:
                        if tok == "&&":
                            parts.append([])
                        else:
                            parts[-1].append(tok)
                    out.append(Command(start, " && ".join(shlex.join(q) for q in parts), parts))
            i += 1
        i += 1
    return out


def _opt(argv: list[str], *names: str) -> list[str]:
    """Every value of the options ``names`` in ``argv`` (``--x v`` and ``--x=v``)."""
    vals = []
    for k, tok in enumerate(argv):
        for n in names:
            if tok == n and k + 1 < len(argv):
                vals.append(argv[k + 1])
            elif tok.startswith(n + "="):
                vals.append(tok.split("=", 1)[1])
    return vals


def _produced(commands: list[Command], upto: Command) -> set[str]:
    """Files earlier README commands write into the working folder (``simulate --out``, ``profile new``)."""
    made: set[str] = set()
    for c in commands:
        if c.line >= upto.line:
            break
        a = c.argv
        if a[:2] == ["pipeline", "simulate"]:
            made.update(_opt(a, "--out"))
        if a[:3] == ["pipeline", "profile", "new"] and len(a) > 3:
            made.add(a[3])
    return made


def classify(cmd: Command, commands: list[Command], shared: bool) -> Plan:
    """How the test treats one README command (see the module docstring); ValueError when it cannot tell."""
    from pipeline.sequences import expand_sequences
    from simulator.world import worlds_dir

    a = cmd.argv
    if a[0] == "export" and len(a) == 2 and "=" in a[1]:
        return Plan("env", "sets a variable; the test sets its own")
    if a[0] == "make" and len(a) == 2:
        if a[1] == "demo":
            return Plan("run", f"its recipe runs first, on the demo shortened to {DEMO_S:g} s")
        return Plan("parse", f"make {a[1]}: the target exists (make test is this suite)")
    if a[0] == "rerun":
        return Plan("run", "a viewer: not opened; its file globs must match the demo run's recordings")
    if a[0] == "evo_ape" and len(cmd.parts) == 2 and cmd.parts[0][0] == "cd":
        return Plan("run", "evo on the TUM export, in the folder the export wrote")
    if a[0] != "pipeline" or len(a) < 2:
        raise ValueError(f"{cmd}: not a command this test knows; classify it in {Path(__file__).name}")
    sub = a[1]
    if sub in LOCAL_SUBCOMMANDS:
        return Plan("run", "needs nothing but the project")
    if sub == "sweep":
        return Plan("parse", "a sweep: the whole pipeline at many parameter points (hours)")
    if sub == "train":
        return Plan("parse", "training a completion network (hours)")
    if sub == "simulate":
        world = _opt(a, "--world")[0]
        duration = _opt(a, "--duration")
        if (worlds_dir() / f"{world}.toml").is_file() and duration and float(duration[0]) <= 60:
            return Plan("run", "a built-in world, a short duration")
        return Plan("parse", "a twin: the whole recorded path (minutes) from the maps under RMAP_ROOT")
    if "--executor" in a and "ray" in _opt(a, "--executor"):
        return Plan("parse", "needs Ray (a local instance or a cluster)")
    if sub == "report":
        if _opt(a, "--sweep"):
            return Plan("parse", "needs a finished sweep (hours)")
        seqs = expand_sequences(",".join(_opt(a, "--seqs", "--seq", "-s")))
        if all(s.name == "demo" for s in seqs):
            return Plan("run", "the demo's evaluate results")
        if all(s.kind == "rmap" for s in seqs):
            return Plan("run" if shared else "parse", "the map scene run earlier" if shared else
                        "the shared maps are absent", needs_shared=True, env={"RMAP_ROOT": str(SHARED_MAPS)})
        raise ValueError(f"{cmd}: report over sequences this test does not run; classify it")
    if sub not in {"run", "status", "view", "export"}:
        raise ValueError(f"{cmd}: subcommand '{sub}' unknown to this test; classify it")
    source = _opt(a, "--source")
    if source:
        if source[0] in _produced(commands, cmd):
            return Plan("run", "on a log an earlier README command wrote")
        return Plan("parse", f"external data: --source {source[0]}")
    seqs = expand_sequences(_opt(a, "--seq", "-s")[0])
    if [s.name for s in seqs] == ["demo"]:
        return Plan("run", "the demo")
    kinds = {s.kind for s in seqs}
    if "coloradar" in kinds:
        return Plan("parse", "recorded ColoRadar logs: needs COLORADAR_ROOT")
    if kinds == {"rmap"}:
        if len(seqs) == 1 and sub == "run":
            return Plan("run" if shared else "parse", "one map scene (about 30 s)" if shared else
                        "the shared maps are absent", needs_shared=True, env={"RMAP_ROOT": str(SHARED_MAPS)})
        return Plan("parse", f"{len(seqs)} map scenes (minutes each)")
    if all(s.scene for s in seqs):
        return Plan("parse", "a twin: simulates its whole path from RMAP_ROOT, then every stage (many minutes)")
    return Plan("parse", f"{len(seqs)} simulated sequences in full (minutes each)")


# -- parsing ----------------------------------------------------------------------------------------------
def _click_context(argv: list[str]) -> Any:
    """Parse ``pipeline ...`` as the CLI does (every option, its type, the required ones); nothing runs.

    A parse error is an AssertionError with the CLI's message (typer may vendor its own click)."""
    import typer.main

    from pipeline.cli import app

    cmd: Any = typer.main.get_command(app)
    ctx = cmd.context_class(cmd, info_name="pipeline")
    name, rest = "pipeline", argv[1:]
    try:
        while hasattr(cmd, "resolve_command"):  # a group: the next word names the subcommand
            name, cmd, rest = cmd.resolve_command(ctx, rest)
            if hasattr(cmd, "resolve_command"):
                ctx = cmd.context_class(cmd, info_name=name, parent=ctx)
        return cmd.make_context(name, list(rest), parent=ctx)
    except Exception as exc:
        if "click" not in type(exc).__module__:
            raise
        message = getattr(exc, "format_message", exc.__str__)()
        raise AssertionError(f"pipeline {shlex.join(argv[1:])}: {message}") from None


def check_parses(cmd: Command, commands: list[Command]) -> None:
    """Raise (core.errors.UserError, AssertionError) when ``cmd`` would not work."""
    from pipeline.config import build_params, load_workflow, parse_set
    from pipeline.profile_cli import available
    from pipeline.registry import load_stages
    from pipeline.sequences import expand_sequences, load_registry
    from sources import mapset, recorded, simulated

    a = cmd.argv
    if a[0] == "export":
        var = a[1].split("=", 1)[0]
        assert var in {recorded.ROOT_VAR, mapset.ROOT_VAR} or var.startswith("RADAR_PIPELINE_"), var
        return
    if a[0] == "make":
        assert re.search(rf"^{re.escape(a[1])}:", (ROOT / "Makefile").read_text(), re.M), f"no target {a[1]}"
        return
    if a[0] in {"rerun", "evo_ape"}:
        return
    ctx = _click_context(a)
    if cmd.argv[1] == "sweep":
        load_workflow(ctx.params["workflow"])
    flags = {"--set": _opt(a, "--set"), "--workflow": _opt(a, "--workflow", "-w"),
             "--world": _opt(a, "--world"), "--dataset": _opt(a, "--dataset")}
    stages = load_stages()
    for stage, values in parse_set(flags["--set"], stages).items():
        build_params(stages[stage], [("--set", values)])
    for wf in flags["--workflow"]:
        if wf in PENDING and not (ROOT / "workflows" / f"{wf}.toml").exists():
            pytest.skip(f"{cmd}: workflows/{wf}.toml is not there yet ({PENDING[wf]})")
        load_workflow(wf)
    if not _opt(a, "--source"):
        for pattern in _opt(a, "--seq", "-s", "--seqs"):
            assert expand_sequences(pattern)
    for world in flags["--world"]:
        spec = load_registry().get(world)
        scene = simulated.twin_scene_of(world, spec.scene if spec is not None else None)
        if scene is None:
            assert not simulated.world_file_missing(world), f"no world '{world}'"
        else:
            scenes = {s.scene for s in load_registry().values() if s.kind == "rmap"}
            assert scene in scenes, f"--world {world}: no map scene '{scene}'"
    for ds in flags["--dataset"]:
        assert ds in available() or ds in _produced(commands, cmd), f"--dataset {ds}: no such profile"
    if a[1] == "profile":
        assert set(_opt(a, "--from")) <= set(available())


COMMANDS = readme_commands(README.read_text())
SHARED = (SHARED_MAPS / "index.json").is_file()


def test_the_readme_has_commands_and_every_one_is_classified() -> None:
    assert len(COMMANDS) >= 30
    plans = [classify(c, COMMANDS, SHARED) for c in COMMANDS]  # raises on an unknown command
    assert sum(p.mode == "run" for p in plans) >= 15


@pytest.mark.parametrize("cmd", COMMANDS, ids=[f"L{c.line}" for c in COMMANDS])
def test_readme_command_parses(cmd: Command) -> None:
    check_parses(cmd, COMMANDS)


def test_a_broken_command_is_caught() -> None:
    """The checks can fail: a misspelt parameter, an unknown option, sequence, world or make target."""
    from core.errors import UserError

    broken = readme_commands("```bash\n"
                             "pipeline run slam --seq demo --set slam.n_particle=20\n"
                             "pipeline run slam --seq demo --set slam.n_particles=many\n"
                             "pipeline export --seq demo --fromat tum\n"
                             "pipeline status --seq 'demoo*'\n"
                             "pipeline simulate --world coloradar_9_twin --out x.bag\n"
                             "pipeline sweep sweep_fig8 --seq demo\n"
                             "make demos\n"
                             "```\n")
    assert len(broken) == 7
    for c in broken:
        with pytest.raises((UserError, AssertionError)):
            check_parses(c, broken)
    with pytest.raises(ValueError, match="classify it"):
        classify(readme_commands("```bash\nfrobnicate --seq demo\n```\n")[0], [], SHARED)


# -- running ----------------------------------------------------------------------------------------------
def _make_demo_recipe() -> list[list[str]]:
    """``make demo``'s recipe lines as pipeline argv (``$(VENV)/bin/pipeline`` -> pipeline, ``$(SEQ)`` -> demo)."""
    text = (ROOT / "Makefile").read_text()
    recipe = re.search(r"^demo:.*\n((?:\t.*\n)+)", text, re.M)
    assert recipe, "Makefile has no demo recipe"
    out = []
    for line in recipe.group(1).splitlines():
        argv = shlex.split(line.strip().replace("$(SEQ)", "demo"))
        assert argv[0].endswith("/bin/pipeline"), line
        out.append(["pipeline", *argv[1:]])
    return out


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """(working folder, environment): a registry whose demo lasts DEMO_S s, an empty cache, ./runs."""
    base = tmp_path_factory.mktemp("readme")
    home = base / "home"
    (home / "data").mkdir(parents=True)
    for p in (ROOT / "data").iterdir():
        if p.name != "sequences.toml":
            (home / "data" / p.name).symlink_to(p)
    (home / "workflows").symlink_to(ROOT / "workflows")
    reg = (ROOT / "data" / "sequences.toml").read_text()
    short = re.sub(r"(\[demo\]\n(?:[^\[\n].*\n)*?duration = )[0-9.]+", rf"\g<1>{DEMO_S}", reg, count=1)
    assert short != reg, "data/sequences.toml: no duration under [demo]"
    (home / "data" / "sequences.toml").write_text(short)
    cwd = base / "cwd"
    cwd.mkdir()
    drop = {"RADAR_PIPELINE_RUNS", "RMAP_ROOT", "DISPLAY", "WAYLAND_DISPLAY"}
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(RADAR_PIPELINE_HOME=str(home), RADAR_PIPELINE_CACHE=str(base / "cache"),
               PYTHONPATH=os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep),
               COLUMNS="160", OMP_NUM_THREADS="1", COLORADAR_ROOT=str(base / "no_coloradar"))
    return cwd, env


def _run(argv: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    exe = [sys.executable, "-m", "pipeline"] if argv[0] == "pipeline" else [
        str(Path(sys.executable).with_name(argv[0]))]
    return subprocess.run([*exe, *argv[1:]], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_runnable_readme_commands_exit_0(workdir: tuple[Path, dict[str, str]]) -> None:
    """make demo's recipe, then every runnable README command in README order, each exit code 0."""
    cwd, env = workdir
    for argv in _make_demo_recipe():
        start = time.monotonic()
        r = _run(argv, cwd, env)
        print(f"{time.monotonic() - start:6.1f} s  make demo: {shlex.join(argv)}")
        assert r.returncode == 0, f"make demo: {shlex.join(argv)}: exit {r.returncode}\n{r.stderr[-3000:]}"
    failures, skipped = [], []
    for cmd in COMMANDS:
        plan = classify(cmd, COMMANDS, SHARED)
        if plan.mode != "run" or cmd.argv[:2] == ["make", "demo"]:
            continue
        wf = _opt(cmd.argv, "--workflow", "-w")
        if wf and wf[0] in PENDING and not (ROOT / "workflows" / f"{wf[0]}.toml").exists():
            skipped.append(f"{cmd} ({PENDING[wf[0]]})")
            continue
        a = cmd.argv
        if a[0] == "rerun":
            matched = [f for g in a[1:] for f in glob.glob(str(cwd / g))]
            if not matched or not all(f.endswith(".rrd") for f in matched):
                failures.append(f"{cmd}: the globs match {matched}")
            continue
        here = cwd / cmd.parts[0][1] if len(cmd.parts) == 2 else cwd
        if a[0] == "evo_ape" and not Path(sys.executable).with_name("evo_ape").exists():
            skipped.append(f"{cmd} (no evo_ape beside {sys.executable})")
            continue
        start = time.monotonic()
        r = _run(a, here, {**env, **plan.env})
        print(f"{time.monotonic() - start:6.1f} s  {cmd}")
        if r.returncode != 0:
            tail = (r.stderr.strip() or r.stdout.strip()).splitlines()[-3:]
            failures.append(f"{cmd}: exit {r.returncode}: " + " | ".join(tail))
    assert not failures, "README commands that fail as printed:\n" + "\n".join(failures)
    if skipped:
        print("not run:\n" + "\n".join(skipped))


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors of a markdown page (lower case, punctuation dropped, spaces to hyphens)."""
    heads = re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", page.read_text(), flags=re.S), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


def test_readme_and_docs_links_resolve() -> None:
    """Relative links of README.md and docs/*.md point at files of the repository, and at their headings."""
    bad = []
    for page in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+://", target):
                continue
            file, _, anchor = target.partition("#")
            path = (page.parent / file).resolve() if file else page
            if not path.exists() or (anchor and path.suffix == ".md" and anchor not in _anchors(path)):
                bad.append(f"{page.relative_to(ROOT)}: {target}")
    assert not bad, bad
