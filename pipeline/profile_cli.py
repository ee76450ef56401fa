"""`pipeline profile new PATH --from NAME`: start a dataset profile for a log the project has never seen.

The new file is a copy of ``data/datasets/<NAME>.toml`` (comments kept) under a new ``name``, with a
header saying what to fill in and how to use it (``--dataset PATH`` with ``--source``, or
``--set ingest.dataset=PATH``). Written to a temporary file and renamed, never over an existing file
unless ``--force``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape

from core.errors import UserError
from core.paths import data_dir
from pipeline.store import write_text_atomic

app = typer.Typer(name="profile", help="dataset profiles: topics, fields, frames and extrinsics of a rig",
                  no_args_is_help=True, add_completion=False)
console = Console(stderr=True)

HEADER = """\
# Dataset profile '{name}', made by `pipeline profile new {path} --from {base}`.
#
# Use it:  pipeline run all --source LOG.bag --dataset {path}
#     or:  pipeline run ingest --seq SEQ --set ingest.dataset={path}
#
# Fill in what your log does not say by itself:
#   [topics]         topic names when the log has several candidates ('' = detected by message type)
#   [radar_fields]   the Doppler field's name if it is none of the listed ones (e.g. "velocity")
#   [frames]         frame names, for streams whose messages carry an empty header.frame_id
#   [extrinsics.*]   the mounting base <- sensor (translation m, quaternion x y z w) when the log has no tf;
#                    without one a sensor is assumed at the base, with a warning
# Clocks need nothing here: ingest.clock.time_source=auto lines up zero, constant or foreign header stamps and
# says what it did (--set ingest.clock.time_source=header|record to choose yourself).
# Single values can also be given per run: --set ingest.frames.radar_extrinsic=[tx,ty,tz,qx,qy,qz,qw],
# --set ingest.frames.radar=NAME, --set ingest.topics.radar=TOPIC (see `pipeline params ingest`).

"""


def available() -> list[str]:
    return sorted(p.stem for p in (data_dir() / "datasets").glob("*.toml"))


def profile_text(base: str, name: str, shown_path: str) -> str:
    """The commented profile text: ``data/datasets/<base>.toml`` renamed to ``name`` with the usage header."""
    src = data_dir() / "datasets" / f"{base}.toml"
    if not src.is_file():
        raise UserError(f"--from '{base}': no such dataset profile ({src}); known: {', '.join(available())}")
    text = src.read_text()
    body, n = re.subn(r'(?m)^name\s*=\s*".*"\s*$', f'name = "{name}"', text, count=1)
    if n == 0:
        body = f'name = "{name}"\n' + text
    return HEADER.format(name=name, path=shown_path, base=base) + body


@app.command("new")
def new(
    path: Annotated[Path, typer.Argument(help="the profile file to write (.toml)")],
    from_: Annotated[str, typer.Option("--from", help="profile to start from (data/datasets/NAME.toml)")] = "generic",
    force: Annotated[bool, typer.Option("--force", help="overwrite an existing file")] = False,
) -> None:
    """Write a commented dataset profile to PATH, to fill in and pass as --dataset PATH."""
    if path.suffix != ".toml":
        raise UserError(f"{path}: a profile file must end in .toml (e.g. my_rig.toml)")
    if path.exists() and not force:
        raise UserError(f"{path} already exists; pass --force to overwrite it")
    if not path.parent.is_dir():
        raise UserError(f"{path}: folder {path.parent} does not exist")
    text = profile_text(from_, path.stem, str(path))
    write_text_atomic(path, text)
    console.print(escape(f"wrote {path} (from '{from_}'); edit [topics], [frames] and [extrinsics.*], then run "
                         f"`pipeline run all --source LOG --dataset {path}`"), soft_wrap=True, highlight=False)
