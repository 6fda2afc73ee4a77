"""Import rules between modules, so the one-direction data flow cannot erode silently.

Every module of edi_live/ and drivers/ is parsed with ast (imports inside functions included) and checked
against the rules below; a failure names the file, line, import and rule.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# top-level import name -> modules (repo-relative path prefixes) allowed to import it
RESTRICTED = {
    "zmq": ("edi_live/publisher.py", "edi_live/client.py"),
    "msgpack": ("edi_live/wire.py",),
    "lz4": ("edi_live/aedat4/",),
    "zstandard": ("edi_live/aedat4/",),
    "flatbuffers": ("edi_live/aedat4/",),
    "usb": ("drivers/davis/transport.py", "drivers/emulator.py", "drivers/davis/discovery.py"),
    "tools": (),
}
PURE_MATH = ("edi_live/edi.py", "edi_live/contrast.py", "edi_live/reconstructor.py", "edi_live/ring.py")
PURE_MATH_ALLOWED = {"numpy", "cv2", "numba", "edi_live"}
PURE_MATH_ALLOWED_EDI = {"edi_live.datatypes", "edi_live.errors", "edi_live.config", "edi_live.edi",
                         "edi_live.contrast", "edi_live._jit"}
DRIVERS_ALLOWED_EDI = ("edi_live.datatypes", "edi_live.source", "edi_live.errors", "edi_live.aedat4",
                       "edi_live.simulation")  # the emulator's generated scene
# the simulator is the ground truth: it must not use the EDI code it is there to judge
SIMULATION_ALLOWED_EDI = ("edi_live.datatypes", "edi_live.errors", "edi_live.aedat4", "edi_live.simulation")


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module


def _violations() -> list[str]:
    import sys

    stdlib = set(sys.stdlib_module_names)
    found = []
    for path in sorted([*REPO.glob("edi_live/**/*.py"), *REPO.glob("drivers/**/*.py")]):
        rel = path.relative_to(REPO).as_posix()
        for line, name in _imports(path):
            top = name.split(".")[0]
            where = f"{rel}:{line} imports {name}"
            allowed = RESTRICTED.get(top)
            if allowed is not None and not rel.startswith(allowed):
                found.append(f"{where}: only {allowed or 'nothing in the packages'} may import {top}")
            if rel in PURE_MATH and top not in stdlib:
                if top not in PURE_MATH_ALLOWED or (top == "edi_live" and name not in PURE_MATH_ALLOWED_EDI):
                    found.append(f"{where}: pure-math modules import only stdlib, numpy, cv2, numba, datatypes")
            if rel.startswith("edi_live/") and top == "drivers" and rel != "edi_live/cli.py":
                found.append(f"{where}: within edi_live only cli.py may import drivers")
            if rel.startswith("edi_live/simulation/") and top == "edi_live" \
                    and not name.startswith(SIMULATION_ALLOWED_EDI):
                found.append(f"{where}: the simulator may use only {SIMULATION_ALLOWED_EDI} from edi_live")
            if rel.startswith("drivers/") and top == "edi_live" and not name.startswith(DRIVERS_ALLOWED_EDI) \
                    and name != "edi_live":
                found.append(f"{where}: drivers may use only {DRIVERS_ALLOWED_EDI} from edi_live")
    return found


def test_import_rules_hold():
    assert _violations() == []


def test_rules_catch_a_violation(tmp_path, monkeypatch):
    # The checker itself must be able to fail: plant a bad import and see it reported.
    bad = REPO / "edi_live" / "_layering_probe_tmp.py"
    bad.write_text("import zmq\nfrom drivers import replay\n")
    sim_bad = REPO / "edi_live" / "simulation" / "_layering_probe_tmp.py"
    sim_bad.write_text("from edi_live import edi\nfrom edi_live.simulation import config\n")
    try:
        found = _violations()
    finally:
        bad.unlink()
        sim_bad.unlink()
    assert any("_layering_probe_tmp.py:1 imports zmq" in v for v in found)
    assert any("_layering_probe_tmp.py:2 imports drivers" in v for v in found)
    assert any("simulation/_layering_probe_tmp.py:1 imports edi_live" in v for v in found)
    assert not any("simulation/_layering_probe_tmp.py:2" in v for v in found)
