"""Loads and stores past their buffer in XLA:CPU's optimised LLVM IR (issue 61).

jaxlib 0.8 and 0.9 miscompile a float64 (R, 4) array padded by one row on x86 (R a multiple of
4, R >= 8): the vectorised loop's exit stores the last row 96 bytes past the buffer. The heap
overflow aborts the process only now and then; this reads the IR that `--xla_dump_to` writes
(`*.ir-with-opt.ll`) and finds such accesses every time.

Each kernel takes its buffers from a table (`load ptr ..., !dereferenceable !K`, K the buffer's
bytes). An access is checked where its address is the buffer plus an offset made of constants
and loop counters (`phi i64 [start, ...], [%next, ...]` with `%next = add %phi, step` and an exit
`icmp eq %next, end`): its offset is evaluated at every corner of the counters' ranges (the
offsets are affine in them) and must lie inside the buffer, unless a conditional branch on the
one path into its block (a scalar compare, or a vector loop's lane mask) excludes that corner.
Addresses it cannot evaluate are passed over: this finds the miscompile's kind of error, it
does not prove a kernel safe.
"""

from __future__ import annotations

import itertools
import pathlib
import re
import sys

BYTES = {"double": 8, "float": 4, "i64": 8, "i32": 4, "i16": 2, "i8": 1, "i1": 1, "half": 2, "bfloat": 2, "ptr": 8}
COMPARE = {
    "ult": int.__lt__,
    "slt": int.__lt__,
    "ule": int.__le__,
    "sle": int.__le__,
    "ugt": int.__gt__,
    "sgt": int.__gt__,
    "uge": int.__ge__,
    "sge": int.__ge__,
    "eq": int.__eq__,
    "ne": int.__ne__,
}
ARITHMETIC = {
    "add": int.__add__,
    "sub": int.__sub__,
    "mul": int.__mul__,
    "or": int.__or__,
    "shl": lambda x, y: x << y if 0 <= y < 64 else None,
}

LABEL = re.compile(r"^([\w.]+):")
DEF = re.compile(r"^\s*(%[\w.]+) = (.*)$")
BRANCH = re.compile(r"\s*br i1 (%[\w.]+), label (%[\w.]+), label (%[\w.]+)")
JUMP = re.compile(r"\s*br label (%[\w.]+)")
STORE = re.compile(r"\s*store (<\d+ x \w+>|\w+) [^,]+, ptr (%[\w.]+)")
LOAD = re.compile(r"\s*%[\w.]+ = load (<\d+ x \w+>|\w+), ptr (%[\w.]+)")
BUFFER = re.compile(r"load ptr, ptr %[\w.]+, align \d+(?:, !invariant.load ![0-9]+)?, !dereferenceable (![0-9]+)")
GEP = re.compile(r"getelementptr (?:inbounds )?(?:nuw )?(?:nusw )?i8, ptr (%[\w.]+), i64 (%?[\w.-]+)")
ARITH = re.compile(r"(add|mul|shl|or|sub) (?:nuw )?(?:nsw )?(?:disjoint )?i64 (%?[\w.-]+), (%?[\w.-]+)")
ICMP = re.compile(r"icmp (?:samesign )?(\w+) i64 (%?[\w.-]+), (%?[\w.-]+)")
PHI = re.compile(r"phi i64 \[ (-?\d+), %[\w.]+ \], \[ (%[\w.]+), %[\w.]+ \]")
LANE = re.compile(r"extractelement <\d+ x i1> (%[\w.]+), i64 (\d+)")
LANE_MASK = re.compile(r"icmp (ult|ule|slt|sle) <\d+ x i\d+> (%[\w.]+), splat \(i\d+ (\d+)\)")
VECTOR_PHI = re.compile(r"phi <\d+ x i\d+> \[ <([^>]*)>, ")


def size_of(type_: str) -> int:
    vector = re.fullmatch(r"<(\d+) x (\w+)>", type_)
    return int(vector.group(1)) * BYTES.get(vector.group(2), 0) if vector else BYTES.get(type_, 0)


class Function:
    def __init__(self, text: str, sizes: dict[str, int]):
        self.defs, self.home, self.entries, self.accesses = {}, {}, {}, []
        block = "entry"
        for line in text.splitlines():
            label = LABEL.match(line)
            if label:
                block = "%" + label.group(1)
            branch = BRANCH.match(line)
            if branch:
                for target, taken in ((branch.group(2), True), (branch.group(3), False)):
                    self.entries.setdefault(target, []).append((block, branch.group(1), taken))
            jump = JUMP.match(line)
            if jump:
                self.entries.setdefault(jump.group(1), []).append((block, None, True))
            d = DEF.match(line)
            if d:
                self.defs[d.group(1)], self.home[d.group(1)] = d.group(2), block
            access = STORE.match(line) or LOAD.match(line)
            if access and size_of(access.group(1)):
                self.accesses.append((access.group(2), size_of(access.group(1)), line.strip(), block))
        self.buffers = {}
        for name, rhs in self.defs.items():
            buffer = BUFFER.match(rhs)
            if buffer and buffer.group(1) in sizes:
                self.buffers[name] = sizes[buffer.group(1)]
        self.loops = {}  # counter -> (first, last)
        for name, rhs in self.defs.items():
            phi = PHI.fullmatch(rhs)
            step = phi and re.fullmatch(
                rf"add (?:nuw )?(?:nsw )?i64 {re.escape(name)}, (\d+)", self.defs.get(phi.group(2), "")
            )
            end = step and re.search(rf"icmp eq i64 {re.escape(phi.group(2))}, (\d+)", text)
            if end:
                self.loops[name] = (int(phi.group(1)), int(end.group(1)) - int(step.group(1)))
        self._depends = {}

    def depends(self, v: str) -> frozenset:
        """The loop counters `v` is computed from (within the arithmetic this understands)."""
        if v not in self._depends:
            self._depends[v] = frozenset()  # cycles (other phis) contribute nothing
            rhs = self.defs.get(v, "")
            if v in self.loops:
                found = frozenset([v])
            else:
                parts = GEP.fullmatch(rhs) or ARITH.fullmatch(rhs) or ICMP.fullmatch(rhs)
                found = (
                    frozenset().union(*(self.depends(a) for a in parts.groups() if a.startswith("%")))
                    if parts
                    else frozenset()
                )
            self._depends[v] = found
        return self._depends[v]

    def value(self, v: str, env: dict):
        """An int, (buffer, byte offset), or None where unknown."""
        if v[0] != "%":
            return int(v) if re.fullmatch(r"-?\d+", v) else None
        if v in env:
            return env[v]
        if v in self.buffers:
            return (v, 0)
        rhs = self.defs.get(v, "")
        gep = GEP.fullmatch(rhs)
        if gep:
            base, offset = self.value(gep.group(1), env), self.value(gep.group(2), env)
            return (base[0], base[1] + offset) if isinstance(base, tuple) and isinstance(offset, int) else None
        arith = ARITH.fullmatch(rhs)
        if arith:
            x, y = self.value(arith.group(2), env), self.value(arith.group(3), env)
            return ARITHMETIC[arith.group(1)](x, y) if isinstance(x, int) and isinstance(y, int) else None
        return None

    def holds(self, cond: str, env: dict):
        rhs = self.defs.get(cond, "")
        lane = LANE.fullmatch(rhs)
        if lane:  # a vectorised loop's lane L: the block's scalar counter plus the induction vector's start
            mask = LANE_MASK.fullmatch(self.defs.get(lane.group(1), ""))
            start = mask and VECTOR_PHI.match(self.defs.get(mask.group(2), ""))
            counter = start and [n for n in env if self.home.get(n) == self.home.get(mask.group(2))]
            if not counter:
                return None
            first = int(start.group(1).split(",")[int(lane.group(2))].split()[-1])
            return COMPARE[mask.group(1)](env[counter[0]] + first, int(mask.group(3)))
        compare = ICMP.fullmatch(rhs)
        if not compare or compare.group(1) not in COMPARE:
            return None
        x, y = self.value(compare.group(2), env), self.value(compare.group(3), env)
        return COMPARE[compare.group(1)](x, y) if isinstance(x, int) and isinstance(y, int) else None

    def reached(self, block: str, env: dict) -> bool:
        """False where a conditional branch on the one path into `block` excludes `env`."""
        seen = set()
        while len(self.entries.get(block, [])) == 1 and block not in seen:
            seen.add(block)
            before, cond, taken = self.entries[block][0]
            if cond is not None and self.holds(cond, env) is (not taken):
                return False
            block = before
        return True

    def guard_counters(self, block: str) -> frozenset:
        found, seen = frozenset(), set()
        while len(self.entries.get(block, [])) == 1 and block not in seen:
            seen.add(block)
            before, cond, _ = self.entries[block][0]
            if cond is not None:
                lane = LANE.fullmatch(self.defs.get(cond, ""))
                mask = lane and LANE_MASK.fullmatch(self.defs.get(lane.group(1), ""))
                if mask:
                    found |= {n for n in self.loops if self.home.get(n) == self.home.get(mask.group(2))}
                else:
                    found |= self.depends(cond)
            block = before
        return found

    def out_of_bounds(self):
        for pointer, size, line, block in self.accesses:
            counters = sorted(self.depends(pointer) | self.guard_counters(block))
            for corner in itertools.product(*(self.loops[n] for n in counters)):
                env = dict(zip(counters, corner, strict=True))
                where = self.value(pointer, env)
                if not isinstance(where, tuple) or not self.reached(block, env):
                    continue
                buffer, offset = where
                if offset < 0 or offset + size > self.buffers[buffer]:
                    yield line, offset, size, self.buffers[buffer]
                    break


def check(text: str) -> list[tuple[str, int, int, int]]:
    """(access, byte offset, bytes, buffer bytes) of every access found past its buffer."""
    sizes = dict(re.findall(r"^(![0-9]+) = !\{i64 (\d+)\}", text, re.M))
    sizes = {k: int(v) for k, v in sizes.items()}
    return [bad for fn in re.split(r"\ndefine ", text)[1:] for bad in Function(fn, sizes).out_of_bounds()]


def check_dir(path) -> list[tuple[str, tuple]]:
    """`check` over every `*.ir-with-opt.ll` that `--xla_dump_to=path` wrote."""
    return [(f.name, bad) for f in sorted(pathlib.Path(path).glob("*ir-with-opt.ll")) for bad in check(f.read_text())]


if __name__ == "__main__":
    for row in check_dir(sys.argv[1]):
        print(row)
