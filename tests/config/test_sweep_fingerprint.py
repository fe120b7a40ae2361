"""`harvest-qp sweep` identifies its experiment by the resolved config, not the file's text."""

from __future__ import annotations

import argparse

import pytest

from harvest_qp.exceptions import ConfigError, InvalidInputError
from harvest_qp.sweep.cli import add_sweep_parser, config_fingerprint, sweep_main


def constant_episode(seed: int) -> dict:
    """A picklable stand-in for `harvest-qp run` (the fingerprint is what is under test)."""
    return {"seed": seed, "success": True, "final_position_error": 0.001 * seed}


def _factory(config, runs_dir, overrides=()):
    return constant_episode


def _sweep(config, out, capsys) -> str:
    parser = argparse.ArgumentParser(prog="harvest-qp")
    add_sweep_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["sweep", str(config), "--seeds", "0:3", "--workers", "1", "--out", str(out), "--quiet",
                              "--no-figures"])
    assert sweep_main(args, episode_for=_factory) == 0
    return capsys.readouterr().out


def test_sweep_resumes_across_cosmetic_edits_and_refuses_a_changed_parent(tmp_path, capsys):
    """Comments, key order and a spelled-out default do not change the experiment (the sweep
    resumes and skips every seed); a changed value in the file it `extends` does (refused).

    Catches: hashing the raw file text (the old fingerprint: a comment forced a re-run, and a
    parent's change went unnoticed, mixing two experiments in one sweep.csv)."""
    parent = tmp_path / "parent.yaml"
    parent.write_text("grasping: {f_d: 3.0}\n")
    child = tmp_path / "child.yaml"
    child.write_text("extends: parent.yaml\nepisode: {duration: 1.0}\n")
    out = tmp_path / "sweep"
    assert "ran 3, skipped 0" in _sweep(child, out, capsys)
    before = config_fingerprint(child)
    child.write_text("# a comment\nepisode:\n  duration: 1.0   # [s]\nextends: parent.yaml\nreaching: {radius: 0.35}\n")
    assert config_fingerprint(child) == before
    assert "ran 0, skipped 3" in _sweep(child, out, capsys)
    parent.write_text("grasping: {f_d: 2.5}\n")  # the child's text is unchanged
    assert config_fingerprint(child) != before
    with pytest.raises(InvalidInputError, match="another experiment"):
        _sweep(child, out, capsys)


def test_sweep_of_a_bad_config_fails_before_any_episode(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("grasping: {k_pq: 1}\n")
    with pytest.raises(ConfigError, match=r"unknown key 'grasping\.k_pq' \(did you mean 'k_pg'\?\)"):
        _sweep(bad, tmp_path / "out", capsys)
    assert not (tmp_path / "out").exists()
