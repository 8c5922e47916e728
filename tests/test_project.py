"""Project-level checks: README's commands, CI entry point, docs in sync with the code, import layering."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

from motion.protocol.reference import markdown_table, markdown_table_v3

ROOT = Path(__file__).resolve().parent.parent

# Lower layers first: a module may import only from its own layer or the layers listed before it.
LAYERS = [
    "motion.errors",
    "motion.closing",
    "motion.protocol",
    "motion.transmission",
    # the configuration's schema and loader: its enums (control mode, halt policy) are what control and safety use
    "motion.config",
    # the arm's Pinocchio model (a package beside motion): it reads the configuration and nothing above it; who in
    # motion may import it is COMPOSITION_ROOTS' to say
    "kinematics",
    "motion.transport",
    "motion.emulator",
    "motion.trajectory",
    "motion.control",
    "motion.safety",
    # homing: its own supervised loop to a hard stop (control and safety below it; the API and CLI use it)
    "motion.homing",
    # what rmd-motion keeps between sessions (turn offsets, identified loops, the drives' record)
    "motion.keep",
    # the one place that builds bus + controller + rate check + supervisor from a configuration
    "motion.compose",
    "motion.telemetry",
    "motion.plot",
    # the live view and replay (viser): reads published snapshots and logs; the arm's shape is injected
    "motion.view",
    "motion.api",
    "motion.demo",
    "motion.cli",
]
# The composition roots: the only modules of motion that may build the Pinocchio model (kinematics), and the emulated
# arm's drives, coupled through it.
COMPOSITION_ROOTS = ("motion.compose", "motion.api", "motion.demo", "motion.cli", "motion.emulator.arm")
# Third-party packages that exactly one subpackage may import.
OWNERS = {
    "can": "motion.transport",
    "serial": "motion.transport",
    "ruckig": "motion.trajectory",
    "yaml": "motion.config",
    "pinocchio": "kinematics",
    "matplotlib": "motion.plot",
    "viser": "motion.view",
    "mcap": "motion.telemetry",
    "mcap_ros2": "motion.telemetry",
}


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```sh\n(.*?)\n```", text, flags=re.S)


def test_readme_has_exactly_two_commands_and_ci_runs_the_second() -> None:
    commands = _readme_commands()
    assert len(commands) == 2
    assert all("\n" not in c for c in commands)
    assert all(c.startswith("python3 -m venv .venv && ") for c in commands)  # whichever python3 is >= 3.11
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    assert ci.count(commands[1]) == 1
    after = [line for line in ci[ci.index(commands[1]) + 1 :] if not line.startswith("#")]
    # Checks may follow; then a failure inside the && list (which `set -e` lets pass) must end the script first.
    assert not after or after[0] == 'status=$?; if [ "$status" -ne 0 ]; then exit "$status"; fi', after[:1]


def test_ci_checks_the_wheel_from_an_empty_directory() -> None:
    ci = (ROOT / ".ci" / "run").read_text()
    for step in ("pip wheel -q --no-deps", 'cd "$work/empty"', 'rmd-motion" demo', 'rmd-motion" init', "-ne 3"):
        assert step in ci, step


def test_docs_protocol_table_matches_the_code() -> None:
    doc = (ROOT / "docs" / "protocol.md").read_text()
    generated = doc.split("<!-- BEGIN GENERATED TABLE -->\n", 1)[1].split("<!-- END GENERATED TABLE -->", 1)[0]
    assert generated == markdown_table(), "regenerate with: python -m motion.protocol"
    v3 = doc.split("<!-- BEGIN GENERATED V3 TABLE -->\n", 1)[1].split("<!-- END GENERATED V3 TABLE -->", 1)[0]
    assert v3 == markdown_table_v3(), "regenerate with: python -m motion.protocol v3"


def _layer(module: str) -> int | None:
    for index, prefix in enumerate(LAYERS):
        if module == prefix or module.startswith(prefix + "."):
            return index
    return None


def _imports(path: Path, module: str) -> list[str]:
    tree = ast.parse(path.read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.rsplit(".", node.level)[0]
                found.append(f"{base}.{node.module}" if node.module else base)
            elif node.module:
                found.append(node.module)
    return found


@pytest.mark.parametrize("package", ["motion", "kinematics"])
def test_imports_point_downward_only(package: str) -> None:
    wrong = []
    for path in sorted((ROOT / package).rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        own = _layer(module)
        for imported in _imports(path, module):
            top = imported.split(".")[0]
            if top in OWNERS and not (module + ".").startswith(OWNERS[top] + "."):
                wrong.append(f"{module} imports {imported} (only {OWNERS[top]} may)")
            if package == "motion" and top == "kinematics" and not module.startswith(COMPOSITION_ROOTS):
                wrong.append(f"{module} imports {imported} (motion never imports kinematics)")
            target = _layer(imported)
            if own is not None and target is not None and target > own:
                wrong.append(f"{module} (layer {LAYERS[own]}) imports {imported} (layer {LAYERS[target]})")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize(
    ("concept", "home"),
    [
        ("WireProtocol", "motion/protocol/table.py"),
        ("ControlMode", "motion/config/schema.py"),
        ("HaltPolicy", "motion/config/schema.py"),
        ("FaultKind", "motion/errors.py"),
        ("ArmState", "motion/safety/states.py"),
    ],
)
def test_one_definition_per_concept(concept: str, home: str) -> None:
    defined = [
        str(path.relative_to(ROOT))
        for package in ("motion", "kinematics", "bench")
        for path in sorted((ROOT / package).rglob("*.py"))
        if re.search(rf"^class {concept}\b", path.read_text(), flags=re.M)
    ]
    assert defined == [home]
    aliased = [
        str(path.relative_to(ROOT))
        for package in ("motion", "kinematics", "bench", "tests")
        for path in sorted((ROOT / package).rglob("*.py"))
        if re.search(rf"\bimport\b[^\n]*\b{concept} as \w+", path.read_text())
    ]
    assert not aliased, f"{concept} imported under another name in {aliased}"


def test_protocol_limits_are_written_only_in_the_protocol_package() -> None:
    # the table's ranges reach the rest through table.field_range / field_names (and scales for the current)
    copies = re.compile(
        r"\b(65535|2147483647|4294967295|42949672\.95|35999)\b|1 << 3[12]|\b2 ?\*\* ?3[12]\b|Range\(0, 255\)|> 0xFF\b"
    )
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for package in ("motion", "kinematics")
        for path in sorted((ROOT / package).rglob("*.py"))
        if "protocol" not in path.relative_to(ROOT).parts
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if copies.search(line)
    ]
    assert not found, "\n".join(found)


def test_protocol_core_is_stdlib_only() -> None:
    allowed = {"__future__", "collections", "dataclasses", "enum", "fractions", "math", "os", "struct", "sys", "typing"}
    allowed.add("motion")
    for path in (ROOT / "motion" / "protocol").rglob("*.py"):
        for imported in _imports(path, "motion.protocol." + path.stem):
            assert imported.split(".")[0] in allowed, f"{path.name} imports {imported}"
            if imported.startswith("motion."):
                allowed_motion = ("motion.protocol", "motion.errors")
                assert imported.startswith(allowed_motion), f"{path.name} imports {imported}"


def test_protocol_demo_prints_decoded_frames(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "motion.cli", "demo", "--protocol"],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "141: a4 00 68 01 28 23 00 00" in result.stdout
    assert "MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=360.0)" in result.stdout
    assert "3 frames, 4 garbage bytes dropped" in result.stdout


def test_every_key_a_configuration_accepts_is_in_the_readmes_configuration_reference() -> None:
    # issue 33 §10: keys accepted but documented nowhere (chain's tip_xyz_m, joint and link; rotor_inertia_kgm2 at
    # joint level) are learnt from error messages. Every key of every section (the schema's fields a file may set)
    # is named in README's "Configuration" section; and the API's bus overrides in its Python API section
    import dataclasses
    import inspect

    from motion.config import schema

    text = (ROOT / "README.md").read_text()
    section = text[text.index("\n## Configuration\n") : text.index("\n## How it works\n")]
    hidden = {"source"}  # (where the configuration was read from: not a key)
    sections = [
        cls
        for _, cls in inspect.getmembers(schema, inspect.isclass)
        if dataclasses.is_dataclass(cls) and cls.__module__ == schema.__name__
    ]
    assert len(sections) >= 10
    missing = [
        f"{cls.__name__}.{f.name}"
        for cls in sections
        for f in dataclasses.fields(cls)
        if not f.metadata.get("derived")
        and f.name not in hidden
        and not re.search(rf"(?<![\w.]){re.escape(f.name)}(?!\w)", section)
    ]
    assert missing == [], f"keys not in README's Configuration section: {missing}"
    api = text[text.index("\n## Python API\n") : text.index("\n## Command line\n")]
    assert "bus_overrides" in api


def test_every_layer_asks_a_control_modes_traits_not_which_mode_it_is() -> None:
    # issue 32 §3: a mode was compared in ~19 modules; a new one would have been taken for torque mode silently. Each
    # layer asks ControlMode.traits (motion/config/schema.py), and every member has its traits and its builder
    from motion.config.schema import ControlMode, ModeTraits
    from motion.control.setpoints import BUILDERS

    compared = re.compile(r"(\bis\b|\bis not\b|==|!=)\s*(schema\.)?ControlMode\.[A-Z]")
    found = [
        f"{path.relative_to(ROOT)}:{number}"
        for path in sorted((ROOT / "motion").rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if compared.search(line)
    ]
    assert found == [], f"modes compared (ask mode.traits): {found}"
    for mode in ControlMode:
        assert isinstance(mode.traits, ModeTraits) and mode in BUILDERS
        assert mode.traits.drive_position_loop != mode.traits.host_torque  # (the two kinds of loop there are)
