"""Shared fixtures."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from motion.keep import STATE_DIR_ENV


@pytest.fixture(autouse=True, scope="session")
def _own_state_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The test run keeps what rmd-motion keeps between sessions (turn offsets, identifications) in a folder of its
    own, which its command-line runs inherit: never the user's. One folder for the run, as one user has one: the
    emulator processes that several tests share keep their arm's turn records from test to test (each emulator is
    on a bus path of its own, and records are per bus)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(STATE_DIR_ENV, str(tmp_path_factory.mktemp("rmd-motion-state")))
        yield
