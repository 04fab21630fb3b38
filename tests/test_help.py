"""`--help` is generated from the config groups and the code (no hand-written list to fall behind), and answers before
any heavy library is imported."""

from __future__ import annotations

import re
import resource
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from contactbench.config import CONFIG_DIR, REPO_ROOT
from contactbench.helptext import number_word
from contactbench.sim.effects import EFFECT_NAMES

# What each entry point's help must list in full: every option of these config groups.
LISTED = {
    "train.py": ("model", "dataset", "budget", "logger", "trainer"),
    "evaluate.py": ("model", "dataset", "budget", "logger"),
    "diagnose.py": ("budget",),
    "generate.py": ("dataset",),
}
HELP_SECONDS = 2.0  # the CPU time `--help` takes (its wall time on an idle machine; a busy one stretches the wall)


def options(group: str) -> list[str]:
    return sorted(path.stem for path in (CONFIG_DIR / group).glob("*.yaml"))


def generated(dataset: str) -> bool:
    return OmegaConf.load(CONFIG_DIR / "dataset" / f"{dataset}.yaml").dataset.scene is not None


def help_text(script: str) -> str:
    done = subprocess.run(
        [sys.executable, str(REPO_ROOT / script), "--help"], capture_output=True, text=True, timeout=120, cwd=REPO_ROOT
    )
    assert done.returncode == 0 and done.stderr == "", done.stderr[-2000:]
    return done.stdout


def option_line(text: str, key: str) -> str | None:
    """The help's `key=...` (up to the next option, three spaces on) with the lines that continue it (indented
    further)."""
    lines = text.splitlines()
    found = next(((i, m) for i, line in enumerate(lines) if (m := re.search(rf"(?:^|\s){key}=", line))), None)
    if found is None:
        return None
    start, match = found
    indent = len(lines[start]) - len(lines[start].lstrip())
    rest = lines[start + 1 :]
    continued = next((i for i, line in enumerate(rest) if len(line) - len(line.lstrip()) <= indent), len(rest))
    first = lines[start][match.start() :].strip().split("   ")[0]
    return " ".join([first, *(line.strip() for line in rest[:continued])])


@pytest.fixture(scope="module")
def helps() -> dict[str, str]:
    return {script: help_text(script) for script in LISTED}


@pytest.mark.parametrize("script", sorted(LISTED))
def test_help_lists_every_option_of_its_config_groups(helps, script):
    text = helps[script]
    for group in LISTED[script]:
        line = option_line(text, group)
        assert line is not None, f"{script} --help has no {group}= line:\n{text}"
        wanted = [o for o in options(group) if group != "dataset" or script != "generate.py" or generated(o)]
        listed = set(re.findall(r"[\w.]+", line.split("=", 1)[1]))
        missing = [option for option in wanted if option not in listed]
        assert not missing, f"{script} --help: {group}= misses {missing}"


def test_generate_help_lists_only_what_it_can_generate(helps):
    line = option_line(helps["generate.py"], "dataset")
    assert "contactnets_cube" not in line and "recordings" not in line.split("(", 1)[0]


def test_diagnose_help_counts_the_effects_the_library_has(helps):
    counted = re.search(r"library of (\w+) effects", helps["diagnose.py"])
    assert counted and counted.group(1) == number_word(len(EFFECT_NAMES)), helps["diagnose.py"]


# One command line per entry point, and the run folder its help must describe (the help's outputs/... template).
COMMANDS = {
    "train.py": ["model=sysid", "variant=frictioncubes_0.5"],
    "evaluate.py": ["model=sysid", "variant=frictioncubes_0.5"],
    "generate.py": ["variant=frictioncubes_0.5"],
    "diagnose.py": ["recordings=assets/contactnets_cube"],
}


@pytest.mark.parametrize("script", sorted(COMMANDS))
def test_help_names_the_folder_a_run_writes(helps, script):
    """The help's `outputs/...` (or `data/...`) folder, its <placeholders> any text, is where Hydra puts the run."""
    from hydra import compose, initialize_config_dir

    text = re.sub(r"\s*\n\s*", "", helps[script])  # a folder may break across lines
    (template,) = re.findall(r"(?:outputs|data)/(?:<[^>]*>|[^\s;()<])+/", text)
    pattern = "".join(".+" if part.startswith("<") else re.escape(part) for part in re.split(r"(<[^>]+>)", template))
    name = script.removesuffix(".py")
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name=name, overrides=COMMANDS[script], return_hydra_config=True)
    folder = Path(cfg.dataset.path if script == "generate.py" else cfg.hydra.run.dir)
    shown = folder.relative_to(REPO_ROOT).as_posix() + "/"
    assert re.fullmatch(pattern, shown), f"{script} --help says {template}; the run goes to {shown}"


@pytest.mark.parametrize("number, word", [(1, "one"), (9, "nine"), (10, "ten"), (12, "twelve"), (22, "22")])
def test_number_words(number, word):
    assert number_word(number) == word


def test_help_answers_in_under_two_seconds_before_any_heavy_import():
    help_text("train.py")  # the first start reads files the next one finds in the page cache
    started, before = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    text = help_text("train.py")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    elapsed, cpu = time.perf_counter() - started, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    print(f"python train.py --help: {elapsed:.2f} s, {cpu:.2f} s of CPU")
    assert text.startswith("train.py ")
    assert cpu < HELP_SECONDS, f"python train.py --help took {cpu:.1f} s of CPU ({elapsed:.1f} s)"
    probe = textwrap.dedent(
        """
        import runpy, sys
        sys.argv = ["train.py", "--help"]
        try:
            runpy.run_path("train.py", run_name="__main__")
        except SystemExit:
            pass
        print(sorted(m for m in ("torch", "pytorch_lightning", "mujoco", "pydrake", "pybullet") if m in sys.modules))
        """
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=REPO_ROOT)
    assert done.stdout.strip().splitlines()[-1] == "[]", done.stdout[-2000:] + done.stderr[-2000:]


def test_help_into_a_closed_pipe_ends_quietly():
    """`python train.py --help | head -1`: the reader is gone before the help is printed; no BrokenPipeError."""
    child = subprocess.Popen(
        [sys.executable, str(REPO_ROOT / "train.py"), "--help"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO_ROOT,
    )
    child.stdout.close()  # the reader has gone before the child prints
    _, stderr = child.communicate(timeout=120)
    assert b"Traceback" not in stderr and b"BrokenPipe" not in stderr, stderr.decode()[-2000:]
