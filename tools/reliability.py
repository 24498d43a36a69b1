"""``make reliability``: bad inputs and injected faults, counted, into bench/reliability.json.

    python tools/reliability.py [--out bench/reliability.json] [--fuzz-examples N]

Three parts, each its own module so that tests can run a part alone:
 - ``tools/reliability_inputs.py``: concrete bad inputs through the real CLI; handled means
   exit 2, one error line naming the file or option, no traceback, nothing already there lost;
 - ``tools/reliability_faults.py``: faults injected into small distributed runs (poisoned
   results, floods, stalling and fake peers, killed clients, unsafe binds, refused keys);
   survived means every frame once with the poses of an undisturbed run, or a clear refusal;
 - the fuzz suite (``tests/test_fuzz.py``) with many more examples than ``make test`` runs.
Exit status 1 when any case was not handled or not survived.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

FUZZ_EXAMPLES = 2000  # hypothesis examples per fuzz test in the long run (make test: far fewer)
FUZZ_TIMEOUT_S = 1800


def run_fuzz(examples: int) -> dict:
    """The fuzz suite with ``examples`` examples per test: {"passed": bool, "seconds", "tail"}."""
    t0 = time.perf_counter()
    env = dict(os.environ, FUZZ_EXAMPLES=str(examples))
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--timeout",
                           str(FUZZ_TIMEOUT_S), str(REPO / "tests" / "test_fuzz.py")], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=FUZZ_TIMEOUT_S + 60)
    tail = (proc.stdout + proc.stderr).strip().splitlines()[-1:] or [""]
    return {"passed": proc.returncode == 0, "examples_per_test": examples,
            "seconds": time.perf_counter() - t0, "outcome": tail[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "reliability.json")
    ap.add_argument("--fuzz-examples", type=int, default=FUZZ_EXAMPLES)
    args = ap.parse_args(argv)
    from reliability_faults import run_faults
    from reliability_inputs import run_bad_inputs

    with tempfile.TemporaryDirectory(prefix="mocap-reliability-") as tmp:
        inputs = run_bad_inputs(Path(tmp) / "inputs")
        faults = run_faults(Path(tmp) / "faults")
    fuzz = run_fuzz(args.fuzz_examples)
    report = {
        "bad_inputs_tried": len(inputs),
        "bad_inputs_handled": sum(1 for c in inputs if c["handled"]),
        "faults_injected": len(faults),
        "faults_survived": sum(1 for c in faults if c["survived"]),
        "fuzz": fuzz,
        "bad_inputs": inputs,
        "faults": faults,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    for kind, cases, ok in (("bad input", inputs, "handled"), ("fault", faults, "survived")):
        for case in cases:
            if not case[ok]:
                print(f"  NOT {ok.upper()}  {kind}: {case['name']}: {case['outcome']}")
    print(f"bad inputs tried {report['bad_inputs_tried']}, handled {report['bad_inputs_handled']}")
    print(f"faults injected {report['faults_injected']}, survived {report['faults_survived']}")
    print(f"fuzz suite ({args.fuzz_examples} examples per test): {'passed' if fuzz['passed'] else 'FAILED'} "
          f"in {fuzz['seconds']:.0f} s")
    print(f"written {args.out}")
    all_ok = (report["bad_inputs_handled"] == report["bad_inputs_tried"]
              and report["faults_survived"] == report["faults_injected"] and fuzz["passed"])
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(main())
