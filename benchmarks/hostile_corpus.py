"""Run the hostile-input corpus (tests/test_hostile.py) and print the counts issue 13 asks for.

    python benchmarks/hostile_corpus.py            # about 3-6 min on 2 shared cores

Every case of the corpus asserts, for its bad input: one clear error (exit status 2 and one 'error:' line from the
command line, or one named ContactbenchError/RecordingsError in process), no traceback, nothing written or changed in
the folder it was pointed at, no payload executed, and (for oversized arrays) a bounded peak memory. A case that
breaks one of these fails; its failure is sorted into the category it broke. The fuzz test is one case of the
corpus here and its examples are counted separately; positive controls (valid input still accepted) are listed apart.
"""

from __future__ import annotations

import re
import resource
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ElementTree
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONTROLS = re.compile(r"accepted|still_reads|readme|custom_variant|resuming")
TIMEOUT_S = 1800


def classify(failure: str) -> str:
    """Which promise a failed case broke, from its failure text."""
    if "TimeoutExpired" in failure or "Timeout" in failure:
        return "hangs"
    if "payload-ran" in failure or "marker.exists" in failure:
        return "code executed"
    if "tree_digest" in failure or ".exists()" in failure:
        return "changed folders"
    if "peak" in failure or "MemoryError" in failure:
        return "memory"
    if "DID NOT RAISE" in failure or "assert 0 == 2" in failure:  # no error where one was due, or exit status 0
        return "silent results"
    if "Traceback" in failure or not failure.lstrip().startswith(("AssertionError", "assert", "E ")):
        return "tracebacks"
    return "unclear errors"


def main() -> int:
    with tempfile.TemporaryDirectory() as folder:
        report = Path(folder) / "junit.xml"
        command = [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            f"--junitxml={report}",
            str(REPO / "tests" / "test_hostile.py"),
        ]
        started = time.monotonic()
        try:
            subprocess.run(command, cwd=REPO, timeout=TIMEOUT_S, capture_output=True, text=True)
            hung = False
        except subprocess.TimeoutExpired:
            hung = True
        elapsed = time.monotonic() - started
        children_peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        cases = ElementTree.parse(report).getroot().iter("testcase") if report.exists() else []
        counts, broken, controls, peaks = Counter(), Counter(), Counter(), {}
        for case in cases:
            name = case.get("name")
            failure = case.find("failure")
            error = case.find("error")
            skipped = case.find("skipped") is not None
            for prop in case.iter("property"):
                if prop.get("name") == "peak_rss_mb":
                    peaks[name] = float(prop.get("value"))
            if CONTROLS.search(name):
                controls["passed" if failure is None and error is None and not skipped else "failed"] += 1
                continue
            counts["cases"] += 1
            if skipped:
                counts["skipped"] += 1
            elif failure is None and error is None:
                counts["clear errors"] += 1
            else:
                node = failure if failure is not None else error
                broken[classify(f"{node.get('message', '')}\n{node.text or ''}")] += 1
    fuzz = re.search(r"max_examples=(\d+)", (REPO / "tests" / "test_hostile.py").read_text())
    worst = max(peaks.items(), key=lambda item: item[1]) if peaks else ("-", float("nan"))
    print(f"hostile corpus (tests/test_hostile.py), {elapsed:.0f} s{' - TIMED OUT' if hung else ''}")
    print(
        f"  cases                {counts['cases']}  (+ {fuzz.group(1) if fuzz else '?'} fuzzed datasets inside one "
        "of them)"
    )
    print(f"  clear errors         {counts['clear errors']}")
    for category in (
        "tracebacks",
        "silent results",
        "hangs",
        "changed folders",
        "code executed",
        "memory",
        "unclear errors",
    ):
        print(f"  {category:<20} {broken[category] + (1 if hung and category == 'hangs' else 0)}")
    print(f"  skipped              {counts['skipped']}")
    print(f"  positive controls    {controls['passed']} passed, {controls['failed']} failed")
    print(
        f"  peak memory, worst refused oversized split: {worst[1]:.1f} MB  ({worst[0]}; reader process, fresh "
        "interpreter)"
    )
    print(f"  peak memory, largest process of the whole run (pytest, torch loaded): {children_peak_mb:.0f} MB")
    return (
        0
        if counts["cases"] and counts["clear errors"] == counts["cases"] and not hung and not controls["failed"]
        else 1
    )


if __name__ == "__main__":
    sys.exit(main())
