"""Importing contactbench changes no global state: matplotlib's backend and settings, MuJoCo's hooks."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import mujoco

from contactbench.sim import rollout

# Runs in a fresh interpreter (pytest has imported everything already): state before and after importing every
# module of the package.
PROBE = """
import importlib, json, pkgutil, sys
import matplotlib, mujoco

def state():
    params = matplotlib.rcParams
    return {
        "backend": repr(dict.__getitem__(params, "backend")),  # raw: reading it through [] would resolve it
        "rcParams": {key: repr(dict.__getitem__(params, key)) for key in params.keys() if key != "backend"},
        "mujoco": {name: repr(getattr(mujoco, "get_mju_user_" + name)()) for name in ("warning", "malloc", "free")},
    }

before = state()
import contactbench
names = [m.name for m in pkgutil.walk_packages(contactbench.__path__, "contactbench.")]
for name in names:
    importlib.import_module(name)
after = state()
print(json.dumps({"modules": len(names), "before": before, "after": after}))
"""


def test_importing_every_module_changes_no_global_state():
    env = {key: value for key, value in os.environ.items() if key != "MPLBACKEND"}  # CI sets it: unset, use() shows
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["modules"] > 40
    before, after = result["before"], result["after"]
    assert after["backend"] == before["backend"], "an import selected a matplotlib backend"
    changed = {k: (v, after["rcParams"].get(k)) for k, v in before["rcParams"].items() if after["rcParams"].get(k) != v}
    assert not changed, f"an import changed matplotlib settings: {changed}"
    assert after["mujoco"] == before["mujoco"], "an import installed a MuJoCo hook"


def test_warning_hook_is_installed_only_while_rolling_out_and_then_restored():
    def mine(message: str) -> None:
        pass

    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(mine)
    try:
        with rollout.counted_warnings():
            assert mujoco.get_mju_user_warning() is rollout._count_warning
            with rollout.counted_warnings():  # overlapping rollouts (a timed-out one still running) share it
                pass
            assert mujoco.get_mju_user_warning() is rollout._count_warning
        assert mujoco.get_mju_user_warning() is mine
    finally:
        mujoco.set_mju_user_warning(previous)
