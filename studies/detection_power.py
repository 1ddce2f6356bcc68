"""Detection-power study of ``jaxlift diagnose`` on logs it was never tuned on.

Every case comes from the independent generator (``studies/detection_generator.py``:
NumPy/SciPy, written from ``docs/model.md``, no jaxlift code) and is diagnosed by the
very call a user makes, ``jaxlift diagnose fit_1.csv fit_2.csv --validate
validation.csv --out DIR`` (from nominal values, iterating until ``none`` or
``undecided``). Resumable: a case whose ``result.json`` exists is not run again, so the
study can run across several sittings::

    python studies/detection_power.py run --data runs/detection/data --out runs/detection
    python studies/detection_power.py report --out runs/detection --to studies/results

``run`` generates the cases it needs (``--cases N``: the first N of the seeded list;
``--only case_007``), ``report`` writes ``detection_power.md``, ``results.csv`` and the
figures (confusion matrix, identification rate against effect size per effect).

Each finished case's ``result.json`` is also kept, small, in the repository
(``--results``, default ``studies/results/detection_cases/case_NNN.json``): a sitting
skips the cases found there, and ``report`` reads them, so the study accumulates across
sittings on fresh machines (``runs/`` holds the generated logs and the diagnosis
folders, and is not committed).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import pathlib
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import matplotlib  # noqa: E402

matplotlib.use("Agg")  # a script writing PNGs (jaxlift itself never switches the backend)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import detection_generator as gen  # noqa: E402

EFFECTS = gen.EFFECTS
#: where each finished case's result is kept (committed; a sitting skips these cases)
RESULTS = "studies/results/detection_cases"


def run_case(
    spec: dict, data_dir: pathlib.Path, out_dir: pathlib.Path, time_limit: float | None = None
) -> dict:
    """Generate (if needed) and diagnose one case; write and return ``result.json``."""
    gen.write_case(spec, data_dir, verbose=False)
    case = data_dir / spec["case_id"]
    res_dir = out_dir / spec["case_id"]
    res_dir.mkdir(parents=True, exist_ok=True)
    argv = [
        "diagnose", str(case / "fit_1.csv"), str(case / "fit_2.csv"),
        "--validate", str(case / "validation.csv"), "--out", str(res_dir / "diagnosis"),
    ]  # fmt: skip
    t0 = time.perf_counter()
    # one process per case, as a user runs it: a long-lived process that diagnoses case
    # after case keeps every compiled model (each log length is a new shape) and ran out
    # of memory after 6 cases (LLVM "Cannot allocate memory", 24 GiB). ``-P``: the
    # working directory is not put before PYTHONPATH, so that a frozen worktree on it is
    # what the case imports also when the study runs from the repository's root (without
    # it the checkout there won: studies/DETECTION.md, twenty-ninth sitting)
    try:
        proc = subprocess.run(
            [sys.executable, "-P", "-m", "jaxlift", *argv],
            capture_output=True, text=True, check=False, timeout=time_limit,
        )  # fmt: skip
        rc, crash = proc.returncode, None
        if rc not in (0, 1, 2):
            crash = f"exit code {rc} (killed or crashed)"
    except subprocess.TimeoutExpired as e:
        # a case that does not finish within the study's limit is a failure, reported
        # in the crash column with this reason (the user would have given up too)
        proc = subprocess.CompletedProcess(e.cmd, None, _text(e.stdout), _text(e.stderr))
        rc, crash = None, f"stopped at the study's time limit of {time_limit:.0f} s"
    err = io.StringIO(proc.stderr)
    wall = time.perf_counter() - t0
    result = {
        "commit": _jaxlift_commit(),
        "library": _jaxlift_library(),
        "jax": jax.__version__,
        "case_id": spec["case_id"],
        "kind": spec["kind"],
        "hidden": spec["hidden_effects"],
        "sizes": spec["effect_sizes"],
        "exit_code": rc,
        "crash": crash,
        "stderr_tail": err.getvalue()[-2000:],
        "stdout_tail": proc.stdout[-2000:],
        "wall_s": wall,
    }
    diag = res_dir / "diagnosis" / "diagnosis.json"
    if rc == 0 and diag.exists():
        d = json.loads(diag.read_text())
        # "kept" since the newcomer's own backward check (2026-12-06): an effect dropped
        # in one step and named again later is kept; before it, the verdicts minus the
        # dropped ones
        kept = d["kept"] if "kept" in d else [v for v in d["verdicts"] if v not in d["dropped"]]
        result.update(
            found=kept,
            final_verdict=d.get("final_verdict", "none"),
            undecided_between=d.get("undecided_between", []),
            baseline_chi2n=d["steps"][0]["base_chi2"] / d["steps"][0]["n_residuals"],
            errors_by_step=d["errors_by_step"],
        )
    (res_dir / "result.json").write_text(json.dumps(result, indent=1))
    return result


def _text(b) -> str:
    return b.decode(errors="replace") if isinstance(b, bytes) else (b or "")


def _jaxlift_dir() -> str:
    """The folder of the jaxlift package that the cases' processes import (the study can
    run from a frozen worktree on PYTHONPATH while development goes on)."""
    code = "import jaxlift, pathlib; print(pathlib.Path(jaxlift.__file__).parent)"
    proc = subprocess.run(
        [sys.executable, "-P", "-c", code], capture_output=True, text=True, check=False
    )
    return proc.stdout.strip() or "."


def _git(where: str, *args: str) -> str:
    proc = subprocess.run(["git", "-C", where, *args], capture_output=True, text=True,
                          check=False)  # fmt: skip
    return proc.stdout.strip() if proc.returncode == 0 else ""


def _dirty(where: str) -> bool:
    return bool(_git(where, "status", "--porcelain", "--", "."))


def _jaxlift_commit() -> str:
    """The git commit of the jaxlift that the cases' processes import."""
    where = _jaxlift_dir()
    rev = _git(where, "rev-parse", "--short", "HEAD")
    return (rev + ("+dirty" if _dirty(where) else "")) or "unknown"


def _jaxlift_library() -> str:
    """The git tree of the ``jaxlift/`` package the cases' processes import (its short
    hash; ``+dirty`` with uncommitted changes there): the code under test. Commits that
    change only tests, studies or documents share it, so a re-run on one library can
    span several commits (and sittings) and still be one measurement."""
    where = _jaxlift_dir()
    tree = _git(where, "rev-parse", "--short", "HEAD:./")
    return (tree + ("+dirty" if _dirty(where) else "")) or "unknown"


def library_of(r: dict) -> str:
    """The library tree a result ran on: recorded since 2026-12-05; for earlier results
    read from the git history through their commit (``?`` when it cannot be)."""
    if r.get("library"):
        return r["library"]
    commit = r.get("commit", "")
    if not commit or commit.endswith("+dirty"):
        return "?"
    root = str(pathlib.Path(__file__).resolve().parents[1])
    return _git(root, "rev-parse", "--short", f"{commit}:jaxlift") or "?"


def outcome(r: dict) -> str:
    """``correct`` / ``undecided`` / ``unexplained`` / ``missed`` / ``wrong`` /
    ``crash`` for one result (``missed``: no wrong name, but not every hidden effect
    found and no reservation either). ``undecided`` and ``unexplained`` are honest
    non-answers (nothing wrong named, the diagnosis says it cannot tell or that
    something none of the candidates
    describes is missing); a wrong name in a diagnosis that ends ``unexplained`` is
    wrong but flagged (the report lists the named effects as possible stand-ins), so
    not confident: see :func:`confident`."""
    if r.get("exit_code") != 0 or "found" not in r:
        return "crash"
    hidden, found = set(r["hidden"]), set(r["found"])
    if found == hidden:
        return "correct"
    if r.get("final_verdict") in ("undecided", "unexplained") and found <= hidden:
        return r["final_verdict"]
    if found < hidden:  # nothing wrong named, a hidden effect not found (too small?)
        return "missed"
    return "wrong"


def confident(r: dict) -> bool:
    """A verdict given without reservation: not ending ``undecided`` or ``unexplained``."""
    return r.get("final_verdict") not in ("undecided", "unexplained")


def cmd_run(args) -> int:
    data, out = pathlib.Path(args.data), pathlib.Path(args.out)
    cases = gen.make_cases(seed=args.seed)
    if args.only:
        cases = [c for c in cases if c["case_id"] in args.only]
    else:
        cases = cases[: args.cases]
    from tqdm.auto import tqdm

    kept = pathlib.Path(args.results)
    if args.library:
        lib = _jaxlift_library()
        if lib != args.library:
            print(
                f"--library {args.library}: the jaxlift imported here is library {lib} "
                f"(from {_jaxlift_dir()}); check out a commit whose jaxlift/ tree is "
                f"{args.library} (git rev-parse --short COMMIT:jaxlift tells; or put a "
                "frozen worktree on PYTHONPATH) so that every case of this re-run tests "
                "the same code",
                file=sys.stderr,
            )
            return 2
    kept.mkdir(parents=True, exist_ok=True)
    for spec in tqdm(cases, desc="detection study", unit="case"):
        if (kept / f"{spec['case_id']}.json").exists():
            continue
        if args.library and _jaxlift_library() != args.library:  # edited meanwhile
            print(f"stopped: jaxlift is no longer library {args.library}", file=sys.stderr)
            return 2
        r = run_case(spec, data, out, time_limit=args.time_limit)
        (kept / f"{spec['case_id']}.json").write_text(json.dumps(r, indent=1))
        tqdm.write(
            f"{spec['case_id']}: hidden {'+'.join(r['hidden']) or 'none'} -> "
            f"{'+'.join(r.get('found', [])) or r.get('final_verdict', r.get('crash'))} "
            f"[{outcome(r)}] {r['wall_s']:.0f} s"
        )
    return 0


def size_at_90(sizes, ok, min_cases: int = 3) -> str:
    """The smallest size from which on (all cases at that size or larger) at least 90 %
    of the cases were identified, with at least ``min_cases`` cases there."""
    pairs = sorted(zip(sizes, ok))
    for i, (s, _) in enumerate(pairs):
        tail = [o for _, o in pairs[i:]]
        if len(tail) >= min_cases and sum(tail) >= 0.9 * len(tail):
            return f"90 % identified from {s:.3g} on ({sum(tail)} of {len(tail)})"
    return f"90 % not reached with >= {min_cases} cases ({len(pairs)} cases so far)"


def _load(kept: pathlib.Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(kept.glob("case_*.json"))]


def cmd_report(args) -> int:
    kept, to = pathlib.Path(args.results), pathlib.Path(args.to)
    to.mkdir(parents=True, exist_ok=True)
    results = _load(kept)
    libraries: dict[str, int] = {}
    for r in results:
        libraries[library_of(r)] = libraries.get(library_of(r), 0) + 1
    if args.library:
        results = [r for r in results if library_of(r) == args.library]
    if not results:
        print(f"no results under {kept}" + (f" on library {args.library}" if args.library
              else ""), file=sys.stderr)  # fmt: skip
        return 1
    with open(to / "results.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case_id", "kind", "hidden", "sizes", "found", "final", "outcome",
                    "baseline_chi2n", "wall_s", "commit", "library"])  # fmt: skip
        for r in results:
            w.writerow([
                r["case_id"], r["kind"], "+".join(r["hidden"]) or "none",
                json.dumps(r["sizes"]), "+".join(r.get("found", [])) or "none",
                r.get("final_verdict", ""), outcome(r),
                f"{r.get('baseline_chi2n', float('nan')):.4g}", f"{r['wall_s']:.1f}",
                r.get("commit", "?"), library_of(r),
            ])  # fmt: skip
    labels = ["none", *EFFECTS, "pair", "crash"]
    conf = np.zeros((len(labels), len(labels)), dtype=int)
    for r in results:
        hidden = r["hidden"][0] if len(r["hidden"]) == 1 else ("pair" if r["hidden"] else "none")
        found = r.get("found", [])
        if outcome(r) == "crash":
            col = "crash"
        elif len(found) == 1:
            col = found[0]
        else:
            col = "pair" if found else "none"
        conf[labels.index(hidden), labels.index(col)] += 1
    fig, ax = plt.subplots(figsize=(9, 7.5))
    ax.imshow(conf, cmap="Blues")
    ax.set_xticks(range(len(labels)), labels, rotation=60, ha="right")
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("found (effects kept at the end)")
    ax.set_ylabel("hidden")
    for i in range(len(labels)):
        for j in range(len(labels)):
            if conf[i, j]:
                ax.text(j, i, str(conf[i, j]), ha="center", va="center", fontsize=8)
    fig.tight_layout()
    fig.savefig(to / "confusion.png", dpi=90)
    plt.close(fig)

    lines = ["# Detection-power study: results", ""]
    n = len(results)
    kinds = {k: [r for r in results if r["kind"] == k] for k in ("null", "single", "pair")}
    times = sorted(r["wall_s"] for r in results)
    lines.append(
        f"{n} cases diagnosed (of the seeded list of 100; the study is resumable). "
        f"Median time per case {times[len(times) // 2]:.0f} s "
        f"(min {times[0]:.0f}, max {times[-1]:.0f}), each case a fresh `jaxlift diagnose` "
        "process, compilation included, on the cores a sitting gave it (studies/DETECTION.md "
        "says per sitting: one or two cores, shared or not)."
    )
    lines.append("")
    lines.append(
        "| case kind | cases | correct | undecided | unexplained | missed | wrong, confident | "
        "wrong, flagged | crash |"
    )
    lines.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for k, rs in kinds.items():
        c = [outcome(r) for r in rs]
        wc = sum(outcome(r) == "wrong" and confident(r) for r in rs)
        lines.append(
            f"| {k} | {len(rs)} | {c.count('correct')} | {c.count('undecided')} | "
            f"{c.count('unexplained')} | {c.count('missed')} | {wc} | {c.count('wrong') - wc} | "
            f"{c.count('crash')} |"
        )
    lines += [
        "",
        "*wrong, flagged*: a wrong effect named on the way by a diagnosis that ends "
        "`unexplained` (the report lists it as a possible stand-in). *wrong, confident*: "
        "a wrong name without reservation.",
    ]
    single = kinds["single"]
    visible = [r for r in single if r.get("baseline_chi2n", 0) >= 1.5]
    if visible:
        c = [outcome(r) for r in visible]
        wc = sum(outcome(r) == "wrong" and confident(r) for r in visible)
        lines += [
            "",
            f"Acceptance, single effects whose baseline misfit is at least 1.5x the noise "
            f"floor (chi2/N >= 1.5): {len(visible)} cases, correct {c.count('correct')} "
            f"({c.count('correct') / len(visible):.0%}; target >= 95 %), wrong-but-confident "
            f"{wc} ({wc / len(visible):.0%}; target <= 2 %).",
        ]
    nulls = kinds["null"]
    if nulls:
        fa = sum(outcome(r) != "correct" for r in nulls)
        lines += [
            "",
            f"Null cases: verdict `none` in {len(nulls) - fa} of {len(nulls)} "
            f"({(len(nulls) - fa) / len(nulls):.0%}; target >= 95 %).",
        ]
    pairs = kinds["pair"]
    if pairs:
        ok = sum(outcome(r) == "correct" for r in pairs)
        lines += [
            "",
            f"Pairs: both found and nothing else kept in {ok} of {len(pairs)} "
            f"({ok / len(pairs):.0%}; target >= 80 %).",
        ]
    commits = sorted({r.get("commit", "?") for r in results})
    lines += ["", f"jaxlift commit(s) the cases ran on: {', '.join(commits)}."]
    used = sorted({library_of(r) for r in results})
    lines += [
        "",
        f"jaxlift library (git tree of `jaxlift/`) the cases ran on: {', '.join(used)}"
        + (" (one code version)." if len(used) == 1 else " (several code versions).")
        + (
            f" Report restricted to library {args.library}; under {kept}: "
            + ", ".join(f"{k} {v} case(s)" for k, v in sorted(libraries.items()))
            + "."
            if args.library
            else ""
        ),
    ]
    lines += ["", "| case | hidden | size | baseline chi2/N | found | final | outcome | time [s] |"]
    lines.append("|---|---|---|---:|---|---|---|---:|")
    for r in results:
        size = ", ".join(f"{v:.3g}" for v in r["sizes"].values()) or "-"
        lines.append(
            f"| {r['case_id']} | {'+'.join(r['hidden']) or 'none'} | {size} | "
            f"{r.get('baseline_chi2n', float('nan')):.3g} | "
            f"{'+'.join(r.get('found', [])) or 'none'} | {r.get('final_verdict', '-')} | "
            f"{outcome(r)} | {r['wall_s']:.0f} |"
        )
    lines += ["", "![confusion matrix](confusion.png)", ""]
    for e in EFFECTS:
        rs = [r for r in single if r["hidden"] == [e]]
        if not rs:
            continue
        fig, ax = plt.subplots(figsize=(5, 3))
        sizes = [r["sizes"][e] for r in rs]
        ok = [outcome(r) == "correct" for r in rs]
        ax.scatter(sizes, ok, c=["tab:green" if o else "tab:red" for o in ok])
        ax.set_xscale("log")
        ax.set_yticks([0, 1], ["missed / wrong", "found"])
        ax.set_xlabel(f"size of {e}")
        ax.set_title(e)
        fig.tight_layout()
        fig.savefig(to / f"rate_{e}.png", dpi=80)
        plt.close(fig)
        found_sizes = sorted(s for s, o in zip(sizes, ok) if o)
        lines.append(
            f"- `{e}`: {sum(ok)} of {len(rs)} found; smallest size found {found_sizes[0]:.3g}; "
            f"{size_at_90(sizes, ok)}"
            if found_sizes
            else f"- `{e}`: 0 of {len(rs)} found"
        )
        lines.append(f"  ![{e}](rate_{e}.png)")
    crashes = [r for r in results if outcome(r) == "crash"]
    if crashes:
        lines += ["", "Crashes:", *(f"- {r['case_id']}: {r['crash'] or r['stderr_tail'][-300:]}"
                                    for r in crashes)]  # fmt: skip
    (to / "detection_power.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="generate and diagnose cases (resumable)")
    r.add_argument("--data", default="runs/detection/data", help="generated logs")
    r.add_argument("--out", default="runs/detection", help="results")
    r.add_argument("--seed", type=int, default=0, help="seed of the case list")
    r.add_argument("--cases", type=int, default=100, help="the first N cases of the list")
    r.add_argument("--only", nargs="*", help="case ids to run")
    r.add_argument(
        "--time-limit", type=float, default=1200.0,
        help="seconds one case may take before it is stopped and counted as failed",
    )  # fmt: skip
    r.add_argument("--results", default=RESULTS, help="each case's result (committed)")
    r.add_argument(
        "--library", help="refuse to run unless the jaxlift imported is this git tree of "
        "jaxlift/ (a re-run on one code version across sittings)",
    )  # fmt: skip
    r.set_defaults(func=cmd_run)
    q = sub.add_parser("report", help="summarise the results")
    q.add_argument("--results", default=RESULTS, help="each case's result, from `run`")
    q.add_argument("--to", default="studies/results", help="where the report goes")
    q.add_argument("--library", help="only the cases run on this git tree of jaxlift/")
    q.set_defaults(func=cmd_report)
    args = p.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
