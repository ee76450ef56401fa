"""`pipeline profile new`: a commented profile that loads, is used with --dataset PATH, and gives extrinsics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from core.errors import UserError
from pipeline.cli import app
from stages.ingest.profile import load_profile


def test_new_profile_from_generic_loads_and_says_how_to_use_it(tmp_path: Path) -> None:
    path = tmp_path / "my_rig.toml"
    res = CliRunner().invoke(app, ["profile", "new", str(path), "--from", "generic"])
    assert res.exit_code == 0, res.output
    text = path.read_text()
    assert f"--dataset {path}" in text and "[extrinsics.*]" in text
    prof = load_profile(str(path))
    assert prof.name == "my_rig"
    assert prof.radar_fields["doppler"] == load_profile("generic").radar_fields["doppler"]
    assert "radar" not in prof.extrinsics.model_fields_set  # left for the user: commented out
    # filled in as the header says, it gives the mounting
    path.write_text(text.replace("# [extrinsics.radar]\n# translation = [0.0, 0.0, 0.0]\n"
                                 "# quaternion = [0.0, 0.0, 0.0, 1.0]",
                                 "[extrinsics.radar]\ntranslation = [0.1, 0.0, 0.2]\n"
                                 "quaternion = [1.0, 0.0, 0.0, 0.0]"))
    prof = load_profile(str(path))
    assert "radar" in prof.extrinsics.model_fields_set
    np.testing.assert_allclose(prof.extrinsics.radar.matrix()[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_new_profile_refuses_to_overwrite_and_unknown_sources(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text("keep")
    runner = CliRunner()
    res = runner.invoke(app, ["profile", "new", str(path)])
    assert isinstance(res.exception, UserError) and "already exists" in str(res.exception)
    assert path.read_text() == "keep"
    assert runner.invoke(app, ["profile", "new", str(path), "--force", "--from", "coloradar"]).exit_code == 0
    assert load_profile(str(path)).topics.radar == load_profile("coloradar").topics.radar
    res = runner.invoke(app, ["profile", "new", str(tmp_path / "x.toml"), "--from", "nosuch"])
    assert isinstance(res.exception, UserError) and "known: " in str(res.exception)
    res = runner.invoke(app, ["profile", "new", str(tmp_path / "x.yaml")])
    assert isinstance(res.exception, UserError) and "must end in .toml" in str(res.exception)
