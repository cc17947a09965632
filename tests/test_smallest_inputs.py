"""Issue 61: the smallest legal inputs in every supported dimension and both precisions,
through the graph builds and the public kernels, each case in a child process so that an abort
in native code is caught as one and names its case.

The children compile with XLA's own settings (not the suite's fast ones, tests/conftest.py:
the miscompile behind issue 61 is made by LLVM's optimisations, which the suite turns off), dump
the optimised LLVM IR of every kernel, and `xla_ir_check` reads it for loads and stores past
their buffer: that finds the miscompile deterministically, where the heap overflow it causes
aborts only now and then (`delaunay` of 6 walkers in 4D: 3 runs in 8).

Default tier (~45 s): every Delaunay size d + 2 ... 3 (d + 1) in d = 2, 3, 4 (open domain,
float64, the precision of the miscompile) and k-NN graphs of k + 1 walkers (k = 1, 4) in
d = 2 ... 8 in every domain, through the graph build. Slow tier: the rest of the grid (float32;
boxed and periodic Delaunay), and every public kernel that takes a graph on the smallest
Delaunay graph of each dimension and on k-NN graphs in d = 2, 5, 8, in both precisions: at
XLA's settings one 4D graph of 6 walkers takes ~110 s through them all, which the default tier
cannot afford.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from xla_ir_check import check_dir

CHILD = Path(__file__).with_name("smallest_inputs_child.py")


def delaunay_cases(dtype, domain, sizes="all"):
    return [
        f"delaunay:{d}:{n}:{dtype}:{domain}"
        for d in (2, 3, 4)
        for n in (range(d + 2, 3 * (d + 1) + 1) if sizes == "all" else [d + 2])
    ]


def knn_cases(dtype, domains=("open", "box", "periodic")):
    return [f"knn:{d}:{k}:{dtype}:{domain}" for domain in domains for d in range(2, 9) for k in (1, 4)]


def child_env(dump: Path) -> dict:
    """The environment without the suite's XLA settings and compile caches, dumping LLVM IR."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("XLA_FLAGS", "JAXGEOM_COMPILE_CACHE_DIR") and not k.startswith("JAX_COMPILATION_CACHE")
    }
    return {**env, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": f"--xla_dump_to={dump}", "JAXGEOM_COMPILE_CACHE": "0"}


def sweep(cases, kernels, workdir: Path, timeout=900):
    """Run `cases` in child processes, restarting after the case in flight when one dies.

    Returns (results by case, [(case, exit status, output tail)] of the deaths, IR findings)."""
    results, deaths, findings, pending = {}, [], [], list(cases)
    read = 0
    while pending:
        dump = workdir / f"xla-{len(results)}"
        proc = subprocess.run(
            [sys.executable, str(CHILD), f"--kernels={kernels}", *pending],
            env=child_env(dump),
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        in_flight = None
        for line in proc.stdout.splitlines():
            if line.startswith("start "):
                in_flight = line.split(" ", 1)[1]
            elif line.startswith("{"):
                row = json.loads(line)
                results[row["case"]] = row
                in_flight = None
        findings += check_dir(dump)
        read += len(list(dump.glob("*ir-with-opt.ll")))
        shutil.rmtree(dump, ignore_errors=True)
        if proc.returncode == 0:
            break
        if in_flight is None:  # died between cases: nothing to skip
            raise AssertionError(f"the child exited {proc.returncode} outside a case:\n{proc.stderr[-3000:]}")
        deaths.append((in_flight, proc.returncode, proc.stderr[-1500:]))
        pending = pending[pending.index(in_flight) + 1 :]
    assert read > 0, "XLA wrote no optimised LLVM IR (*ir-with-opt.ll) to read: the IR check would pass unread"
    return results, deaths, findings


def check_sweep(cases, kernels, workdir):
    results, deaths, findings = sweep(cases, kernels, workdir)
    assert not deaths, "cases that killed their process:\n" + "\n".join(
        f"{c} (exit {rc}):\n{tail}" for c, rc, tail in deaths
    )
    assert not findings, f"XLA:CPU kernels reading or writing past their buffers: {findings[:5]}"
    assert set(results) == set(cases)
    failed = {c: r["graph"] for c, r in results.items() if r["graph"] != "ok"}
    assert not failed, f"smallest legal inputs refused by the graph build: {failed}"
    raw = {(c, k): o for c, r in results.items() for k, o in r["kernels"].items() if o.startswith("raw")}
    assert not raw, f"kernels that raised something other than a clear ValueError/TypeError: {raw}"
    return results


def test_smallest_graphs_build_in_every_dimension(tmp_path):
    check_sweep(delaunay_cases("float64", "open") + knn_cases("float64"), "none", tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_smallest_graphs_build_in_every_domain_and_precision(tmp_path, dtype):
    cases = delaunay_cases(dtype, "box") + delaunay_cases(dtype, "periodic")
    if dtype == "float32":
        cases += delaunay_cases(dtype, "open") + knn_cases(dtype)
    check_sweep(cases, "none", tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_smallest_graphs_through_every_public_kernel(tmp_path, dtype):
    cases = delaunay_cases(dtype, "open", sizes="smallest") + [f"knn:{d}:4:{dtype}:open" for d in (2, 5, 8)]
    results = check_sweep(cases, "all", tmp_path)
    outcomes = {}
    for row in results.values():
        for name, outcome in row["kernels"].items():
            outcomes.setdefault(name, set()).add(outcome)
    never_ran = sorted(name for name, seen in outcomes.items() if "ok" not in seen)
    assert not never_ran, f"kernels that no smallest graph ran (each refused them all): {never_ran}"


def test_the_ir_check_finds_an_access_past_a_buffer():
    """The checker on a hand-made kernel with the miscompile's shape: a store 96 bytes past a
    544-byte buffer is found, one inside it is not."""
    kernel = """
define ptr @k(ptr %0) {
  %1 = getelementptr inbounds nuw i8, ptr %0, i64 24
  %2 = load ptr, ptr %1, align 8, !invariant.load !1
  %3 = load ptr, ptr %2, align 8, !invariant.load !1, !dereferenceable !2
  %4 = getelementptr i8, ptr %3, i64 {offset}
  store double 0.0, ptr %4, align 8
  ret ptr null
}
!1 = !{}
!2 = !{i64 544}
"""
    from xla_ir_check import check

    assert check(kernel.replace("{offset}", "608"))
    assert not check(kernel.replace("{offset}", "536"))
