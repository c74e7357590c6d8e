"""Every subpackage of fastmem ships: setup.cfg lists it (a missing one installs without it)."""

import configparser
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_setup_cfg_lists_every_subpackage():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    listed = {p.strip() for p in cfg["options"]["packages"].split() if p.strip()}
    found = {
        "fastmem." + init.parent.relative_to(ROOT / "fastmem").as_posix().replace("/", ".")
        for init in (ROOT / "fastmem").rglob("__init__.py")
        if init.parent != ROOT / "fastmem"
    }
    assert found, "no subpackage found: the test reads the wrong folder"
    assert found - listed == set(), f"setup.cfg [options] packages lacks {sorted(found - listed)}"
