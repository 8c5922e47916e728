"""The README's walk from `rmd-motion init` to a first move (issue 33), command by command, against the emulator: the
offline steps in this process, the others over a slcan pseudo-terminal to `rmd-motion emulate` (real time: on a host
too busy for any rate the moving steps are skipped, saying so)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.motion_rig import skip_if_rate_refused
from tests.test_cli import ROOT, cli, config_at, running_emulator

pytestmark = pytest.mark.realtime

README = (ROOT / "README.md").read_text()


def _walk() -> list[list[str]]:
    """The walk's commands as the README writes them (its `rmd-motion ...` lines, comments and $EDITOR left out)."""
    section = README.split("## A new arm, step by step", 1)[1].split("```text", 1)[1].split("```", 1)[0]
    return [re.sub(r"\s+#.*$", "", line).split()[1:] for line in section.splitlines() if line.startswith("rmd-motion")]


def test_the_readme_walks_a_new_arm_from_init_to_a_first_move(tmp_path: Path) -> None:
    steps = _walk()
    assert [step[0] for step in steps] == ["init", "check", "run", "scan", "check", "check", "jog", "move"]
    for step in steps[:3]:  # init, the offline check, the dry run: no hardware
        result = cli(*step, cwd=tmp_path)
        assert result.returncode == 0, (step, result.stderr)
    assert (tmp_path / "my-arm" / "programs" / "arm2.yaml").is_file()
    config = tmp_path / "my-arm" / "arm2.yaml"
    with running_emulator(tmp_path, config, "--slcan-link") as emulated:
        fit = config_at(config, tmp_path / "my-arm", 20.0)  # (a rate a busy host holds: the walk is not about speed)
        for step in steps[3:]:
            args = [str(fit) if arg == "my-arm/arm2.yaml" else arg for arg in step]
            result = cli(*args, *emulated.bus_args, cwd=tmp_path)
            skip_if_rate_refused(result)
            assert result.returncode == 0, (step, result.stderr)
        assert "shoulder=10.0" in result.stdout or "shoulder=9.9" in result.stdout or "shoulder=10" in result.stdout
