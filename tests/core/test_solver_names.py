"""A QP backend name is checked when the solver is configured, not on every control step.

Catches: ``Solver("nosuch")`` / ``qp.solver: nosuch`` accepted and then every step falling
back to the safe stop (or silently to the backup backend) with "SolverNotAvailableError".
"""

from __future__ import annotations

import pytest

from harvest_qp.cli import main
from harvest_qp.exceptions import HarvestQPError, SolverNotAvailableError
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.solver import Solver


@pytest.mark.parametrize("name", ["nosuch", "qpsolvers:nosuch", "", 3, None])
def test_solver_rejects_an_unknown_backend_at_construction(name):
    with pytest.raises(SolverNotAvailableError, match="backend") as info:
        Solver(name)
    assert isinstance(info.value, HarvestQPError)


def test_fallback_typo_is_an_error_but_an_uninstalled_qpsolvers_fallback_is_skipped():
    with pytest.raises(SolverNotAvailableError, match="fallback_backends: unknown QP backend 'proxsuit'"):
        Solver("daqp", fallback_backends=["proxsuit"])
    assert Solver("daqp", fallback_backends=["proxsuite", "qpsolvers:not_installed_here"]).backend_name == "daqp"


@pytest.mark.parametrize("override", ["qp.solver=nosuch", "qp.backup_solver=nosuch", "qp.solver=qpsolvers:nosuch"])
def test_check_config_names_the_bad_backend_with_exit_code_2(override, capsys):
    code = main(["check-config", str(tasks_dir() / "paper.yaml"), "--set", override])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and override.split("=")[0] in err and "nosuch" in err


def test_ctrl_c_ends_the_cli_with_one_line_and_code_130(monkeypatch, capsys):
    """Ctrl-C during `harvest-qp run` (e.g. with the live viewer) ends with one line, exit 130,
    no traceback (the audit saw a full KeyboardInterrupt traceback)."""
    import harvest_qp.cli as cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "run_paper", interrupted)
    assert cli.main(["run", str(tasks_dir() / "paper.yaml")]) == 130
    err = capsys.readouterr().err
    assert err == "harvest-qp: run interrupted (Ctrl-C)\n"
