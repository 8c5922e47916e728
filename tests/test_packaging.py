"""The package carries its examples: lookup through importlib.resources, the naming rule, ``rmd-motion init``, and
the version. (Building a wheel and running the demo from it is too slow for the suite: `.ci/run` does that.)"""

from __future__ import annotations

import importlib.metadata
import importlib.resources
import tomllib
from pathlib import Path

import pytest

import motion
from motion.cli import main
from motion.config import example_config, example_names, load_config, load_config_or_example, resolve_config
from motion.config.examples import copy_examples, example_files, examples_dir
from motion.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
EXAMPLES = (
    "arm2.yaml", "arm2_rs485.yaml", "arm6.urdf", "arm6.yaml", "arm6_v3.yaml", "bench1.yaml", "bimanual.urdf",
    "bimanual.yaml",
)  # fmt: skip


def test_the_examples_are_package_data_of_motion_found_through_importlib_resources() -> None:
    packaged = importlib.resources.files("motion") / "examples"
    assert examples_dir() == packaged
    assert [p.name for p in example_files()] == list(EXAMPLES)
    assert example_names() == (
        "arm2.yaml", "arm2_rs485.yaml", "arm6.yaml", "arm6_v3.yaml", "bench1.yaml", "bimanual.yaml"
    )  # fmt: skip
    # configs/ is their only copy: in a checkout motion/examples leads there.
    assert examples_dir().resolve() == CONFIGS.resolve()


def test_pyproject_ships_every_example_as_package_data() -> None:
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = setuptools["package-data"]["motion.examples"]
    assert {f"*{p.suffix}" for p in example_files()} <= set(patterns)
    assert setuptools["dynamic"]["version"] == {"attr": "motion.__version__"}


def test_every_example_loads_from_the_package_with_its_urdf() -> None:
    for name in example_names():
        config = load_config(example_config(name))
        assert config.source == str(examples_dir() / name)
    arm6 = load_config(example_config("arm6.yaml"))
    assert arm6.model.urdf == (examples_dir() / "arm6.urdf").resolve()


def test_an_unknown_example_names_the_examples() -> None:
    with pytest.raises(ConfigError, match=r"arm9.yaml: <file>: no example .* the examples are arm2.yaml, arm2_rs485"):
        example_config("arm9.yaml")


def test_a_file_that_exists_is_always_the_one_used(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").mkdir()
    mine = tmp_path / "configs" / "arm2.yaml"
    mine.write_text((CONFIGS / "arm2.yaml").read_text().replace("name: arm2", "name: my_arm"))
    for name in ("configs/arm2.yaml", "./configs/arm2.yaml", mine):
        assert resolve_config(name) == Path(name)
        assert load_config_or_example(name).name == "my_arm"
    # A broken file of the user's is reported, never replaced by the example.
    mine.write_text("name: [")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config_or_example("configs/arm2.yaml")


@pytest.mark.parametrize("name", ["arm2.yaml", "configs/arm2.yaml", "./configs/arm2.yaml"])
def test_an_example_name_that_is_no_file_here_is_the_packaged_example(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert resolve_config(name) == examples_dir() / "arm2.yaml"
    assert load_config_or_example(name).name == "arm2"


@pytest.mark.parametrize("name", ["other/arm2.yaml", "configs/sub/arm2.yaml", "/nowhere/configs/arm2.yaml"])
def test_other_paths_never_fall_back_to_an_example(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert resolve_config(name) == Path(name)
    with pytest.raises(ConfigError, match=f"{name}: <file>: file not found$"):
        load_config_or_example(name)


def test_a_missing_example_name_lists_the_examples(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    message = "configs/arm9.yaml: <file>: file not found, and no example configuration has that name (arm2.yaml, "
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        resolve_config("configs/arm9.yaml")


# ---------------------------------------------------------------------------------------------------- init


def _tree(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def test_init_copies_the_examples_into_configs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["init"]) == 0
    assert _tree(tmp_path / "configs") == _tree(CONFIGS)
    out = capsys.readouterr().out
    assert "wrote configs/arm6.urdf" in out
    # The copy is the user's now, and loads with its URDF from beside it.
    arm6 = load_config_or_example("configs/arm6.yaml")
    assert arm6.source == "configs/arm6.yaml"
    assert arm6.model.urdf == tmp_path / "configs" / "arm6.urdf"
    # Again: nothing differs, nothing is rewritten.
    assert main(["init"]) == 0
    there = (
        "already there: arm2.yaml, arm2_rs485.yaml, arm6.urdf, arm6.yaml, arm6_v3.yaml, bench1.yaml, bimanual.urdf, "
        "bimanual.yaml, programs/arm2"
    )
    out = capsys.readouterr().out
    assert there in out and "programs/bench1.yaml" in out
    # ... with a program per example arm, which runs from there as it is named in the README
    assert sorted(p.name for p in (tmp_path / "configs" / "programs").iterdir()) == sorted(
        p.name for p in CONFIGS.glob("*.yaml")
    )


def test_init_refuses_to_overwrite_an_edited_file_unless_forced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "my arm"
    assert main(["init", str(target)]) == 0
    edited = (target / "arm6.yaml").read_text() + "# mine\n"
    (target / "arm6.yaml").write_text(edited)
    (target / "arm2.yaml").unlink()
    capsys.readouterr()

    assert main(["init", str(target)]) == 2
    err = capsys.readouterr().err
    assert f"{target}: files already there with other contents: arm6.yaml; nothing was copied" in err
    assert "--force overwrites them" in err
    assert (target / "arm6.yaml").read_text() == edited
    assert not (target / "arm2.yaml").exists()  # nothing at all was written

    assert main(["init", str(target), "--force"]) == 0
    assert _tree(target) == _tree(CONFIGS)


def test_init_into_something_other_than_a_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "file").write_text("")
    assert main(["init", str(tmp_path / "file")]) == 2
    assert f"{tmp_path / 'file'} is not a directory" in capsys.readouterr().err


def test_copy_examples_replaces_a_link_instead_of_writing_through_it(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere.yaml"
    elsewhere.write_text("keep")
    target = tmp_path / "configs"
    target.mkdir()
    (target / "arm2.yaml").symlink_to(elsewhere)
    with pytest.raises(FileExistsError, match="arm2.yaml"):
        copy_examples(target)
    copied = copy_examples(target, overwrite=True)
    assert target / "arm2.yaml" in copied.written
    assert elsewhere.read_text() == "keep"
    assert not (target / "arm2.yaml").is_symlink()


# ---------------------------------------------------------------------------------------------------- version


def test_version_is_the_package_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    version = importlib.metadata.version("rmd-motion")
    assert capsys.readouterr().out == f"rmd-motion {version}\n"
    assert motion.__version__ == importlib.metadata.version("rmd-motion")


def test_changelog_has_this_release() -> None:
    assert f"## {motion.__version__} " in (ROOT / "CHANGELOG.md").read_text()


def test_license_file_is_the_declared_license() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT"
    assert project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert "urls" not in project  # none invented: added when the project has public addresses
