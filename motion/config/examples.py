"""The example configurations shipped with the package, and the rule that lets a command name one.

The examples (``arm2.yaml``, ``arm6.yaml`` with ``arm6.urdf``, ...) have one copy, the repository's top-level
``configs/``; ``motion/examples`` is a symbolic link to it, so that a source checkout, an editable install and an
installed wheel (where setuptools copied the files in as package data) all find them as the directory ``examples``
of the ``motion`` package, through :mod:`importlib.resources`. The configurations name their URDF relative to
themselves, which holds in every one of these places.

Naming a configuration (:func:`resolve_config`): the file the user named is used whenever it exists. Only when it
does not, and it is written as an example's bare name (``arm2.yaml``) or as ``configs/NAME`` (the layout of a checkout
and of ``rmd-motion init``), the packaged example ``NAME`` stands in, so the commands and the examples of the
documentation work from any directory.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
from pathlib import Path
from typing import Final

from motion.config.loader import load_config
from motion.config.schema import ArmConfig
from motion.errors import ConfigError

#: The package whose directory :data:`EXAMPLES_DIR` holds the examples.
EXAMPLES_PACKAGE: Final = "motion"
EXAMPLES_DIR: Final = "examples"
#: The directory the examples live in within a checkout, and where ``rmd-motion init`` puts them by default.
CONFIGS_DIR: Final = "configs"
#: What an example file is: a configuration or a URDF it names.
CONFIG_SUFFIX: Final = ".yaml"
EXAMPLE_SUFFIXES: Final = (CONFIG_SUFFIX, ".urdf")
#: The subdirectory of the examples with a motion program per example arm (``programs/arm2.yaml`` for ``arm2.yaml``).
PROGRAMS_DIR: Final = "programs"


def examples_dir() -> Path:
    """The directory of the packaged examples.

    Raises:
        ConfigError: the package is not installed as plain files (a zip archive), or its examples are missing.
    """
    root = importlib.resources.files(EXAMPLES_PACKAGE) / EXAMPLES_DIR
    if not isinstance(root, Path) or not root.is_dir():
        raise ConfigError(
            str(root),
            "<file>",
            "the example configurations are not installed as files: reinstall rmd-motion from a wheel or a checkout "
            "(on a checkout without symbolic links, motion/examples must lead to configs/)",
        )
    return root


def example_files() -> tuple[Path, ...]:
    """Every example file (configurations and URDFs), sorted by name.

    Raises:
        ConfigError: see :func:`examples_dir`.
    """
    return tuple(sorted(p for p in examples_dir().iterdir() if p.suffix in EXAMPLE_SUFFIXES and p.is_file()))


def example_programs() -> tuple[Path, ...]:
    """The example motion programs (``rmd-motion run``), one per example arm, named after it; sorted.

    Raises:
        ConfigError: see :func:`examples_dir`.
    """
    directory = examples_dir() / PROGRAMS_DIR
    return tuple(sorted(p for p in directory.iterdir() if p.suffix == CONFIG_SUFFIX and p.is_file()))


def example_names() -> tuple[str, ...]:
    """The file names of the example configurations (``arm2.yaml``, ...), sorted.

    Raises:
        ConfigError: see :func:`examples_dir`.
    """
    return tuple(p.name for p in example_files() if p.suffix == CONFIG_SUFFIX)


def example_config(name: str) -> Path:
    """The packaged example configuration ``name`` (a file name such as ``arm6.yaml``).

    Raises:
        ConfigError: no example of that name (the message lists the examples).
    """
    names = example_names()
    if name not in names:
        raise ConfigError(name, "<file>", f"no example configuration of that name; the examples are {', '.join(names)}")
    return examples_dir() / name


def resolve_config(path: str | os.PathLike[str]) -> Path:
    """The file a configuration name stands for (the rule is in the module docstring).

    Returns:
        ``path`` itself when it exists or is no example's name (then loading it reports what is wrong with it), else
        the packaged example of that name.

    Raises:
        ConfigError: ``path`` does not exist, is written like an example's name, and no example has that name (the
            message lists the examples).
    """
    file = Path(path)
    by_name = not file.is_absolute() and file.parent in (Path(), Path(CONFIGS_DIR))
    if file.exists() or not by_name:
        return file
    names = example_names()
    if file.name not in names:
        raise ConfigError(
            str(file), "<file>", f"file not found, and no example configuration has that name ({', '.join(names)})"
        )
    return examples_dir() / file.name


def resolve_program(path: str | os.PathLike[str]) -> Path:
    """The file a program name stands for: as :func:`resolve_config`, with the example programs standing in for
    ``programs/NAME`` and ``configs/programs/NAME`` where no such file exists.

    Raises:
        ConfigError: ``path`` does not exist, is written like an example program's name, and no example program has
            that name (the message lists them).
    """
    file = Path(path)
    by_name = not file.is_absolute() and file.parent in (Path(PROGRAMS_DIR), Path(CONFIGS_DIR) / PROGRAMS_DIR)
    if file.exists() or not by_name:
        return file
    programs = {p.name: p for p in example_programs()}
    if file.name not in programs:
        raise ConfigError(
            str(file), "<file>", f"file not found, and no example program has that name ({', '.join(programs)})"
        )
    return programs[file.name]


def load_config_or_example(path: str | os.PathLike[str]) -> ArmConfig:
    """Load the configuration ``path`` names (:func:`resolve_config`), validated.

    Raises:
        ConfigError: the file is missing or invalid.
    """
    return load_config(resolve_config(path))


@dataclasses.dataclass(frozen=True, slots=True)
class CopiedExamples:
    """What :func:`copy_examples` did.

    Attributes:
        written: the files it wrote.
        unchanged: the files that were there already with the example's contents (not rewritten).
    """

    written: tuple[Path, ...]
    unchanged: tuple[Path, ...]


def copy_examples(target: str | os.PathLike[str], *, overwrite: bool = False) -> CopiedExamples:
    """Copy every example (configurations and URDFs, and the programs into ``programs/``) into the directory
    ``target``, created if needed.

    Args:
        target: the directory.
        overwrite: replace files of the same names whose contents differ; without it such a file stops the copy
            before anything is written.

    Raises:
        FileExistsError: files of the same names with other contents are there and ``overwrite`` is false (the
            message names them); nothing was written.
        NotADirectoryError: ``target`` is something other than a directory.
        OSError: the directory or a file cannot be written.
        ConfigError: see :func:`examples_dir`.
    """
    directory = Path(target)
    if directory.exists() and not directory.is_dir():
        raise NotADirectoryError(f"{directory} is not a directory")
    plan = [(source, directory / source.name) for source in example_files()]
    plan += [(source, directory / PROGRAMS_DIR / source.name) for source in example_programs()]
    unchanged = [dest for source, dest in plan if dest.is_file() and dest.read_bytes() == source.read_bytes()]
    changed = [(source, dest) for source, dest in plan if dest not in unchanged]
    clashes = [str(dest.relative_to(directory)) for _, dest in changed if dest.exists() or dest.is_symlink()]
    if clashes and not overwrite:
        raise FileExistsError(
            f"{directory}: files already there with other contents: {', '.join(clashes)}; nothing was copied"
        )
    for source, dest in changed:
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.unlink(missing_ok=True)  # a link is replaced, not followed to a file elsewhere
        dest.write_bytes(source.read_bytes())
    return CopiedExamples(tuple(dest for _, dest in changed), tuple(unchanged))
