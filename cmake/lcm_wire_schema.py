#!/usr/bin/env python3
"""Writes the wire schemas of .lcm message types as a C++ source for services/common/wire_guard.

    lcm_wire_schema.py FUNCTION OUT.cc FILE.lcm... [--legacy FILE.lcm...]

OUT.cc defines `FUNCTION()`, the schemas of the FILEs, and `FUNCTIONLegacy()`, the older versions
given after --legacy (lcmtypes/legacy/, none without it): each one's fingerprint, the current
type's name ("ftcal." and its struct's) and what the version is (its `// ftcal-legacy: ...` line),
for the guard's refusal of a wrong fingerprint to name it and the command that converts the log.

The guard walks a received message's bytes with these tables before LCM's generated decoder
sees them (wire_guard.h says why). The tables come from the same .lcm files as lcm-gen's code,
so a changed message definition changes its schema with it; each table carries the fingerprint
computed here with lcm-gen's hash (lcmgen.c, lcm_struct_hash), and wire_guard_test checks it
against the generated class's getHash(): a parse that differs from lcm-gen's fails there.

Only what ftcal's types use is accepted: primitive members, fixed or member-sized dimensions.
A member of struct type (nesting) stops the build with its name, rather than a schema that
cannot describe it.
"""
import re
import sys

PRIMITIVES = {
    "int8_t": "kInt8", "int16_t": "kInt16", "int32_t": "kInt32", "int64_t": "kInt64",
    "byte": "kByte", "boolean": "kBoolean", "float": "kFloat", "double": "kDouble",
    "string": "kString",
}
INTEGERS = {"int8_t", "int16_t", "int32_t", "int64_t"}
MASK = (1 << 64) - 1


def signed64(v):
    v &= MASK
    return v - (1 << 64) if v >> 63 else v


def hash_update(v, c):
    # lcm-gen: v = ((v<<8) ^ (v>>55)) + c on int64_t; c is a (signed) char.
    c = c - 256 if c > 127 else c
    return signed64(((v << 8) ^ (v >> 55)) + c)


def hash_string(v, s):
    v = hash_update(v, len(s))
    for ch in s.encode():
        v = hash_update(v, ch)
    return v


def legacy_line(path):
    m = re.search(r"^//\s*ftcal-legacy:\s*(.+?)\s*$", open(path, encoding="utf-8").read(), re.M)
    if not m:
        sys.exit(f"{path}: a legacy version needs a line '// ftcal-legacy: what it is'")
    return m.group(1)


def c_string(s):
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def parse(path):
    text = open(path, encoding="utf-8").read()
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    package = re.search(r"\bpackage\s+([\w.]+)\s*;", text)
    structs = re.findall(r"\bstruct\s+(\w+)\s*\{(.*?)\}", text, flags=re.S)
    if len(structs) != 1:
        sys.exit(f"{path}: expected one struct, found {len(structs)}")
    name, body = structs[0]
    members = []
    caps = {}
    for decl in body.split(";"):
        decl = decl.strip()
        if decl.startswith("const "):
            # `const intN_t MAX_<MEMBER> = v` caps the integer member that sizes arrays.
            c = re.fullmatch(r"const\s+int\d+_t\s+MAX_(\w+)\s*=\s*(\d+)", decl)
            if c:
                caps[c.group(1).lower()] = int(c.group(2))
            continue
        if not decl:
            continue
        m = re.fullmatch(r"([\w.]+)\s+(\w+)\s*((?:\[\s*\w+\s*\]\s*)*)", decl)
        if not m:
            sys.exit(f"{path}: cannot parse member '{decl}'")
        typ, member, dims_text = m.groups()
        if typ not in PRIMITIVES:
            sys.exit(f"{path}: member '{member}' has type '{typ}': the wire guard takes "
                     "primitive members only (extend cmake/lcm_wire_schema.py and wire_guard)")
        dims = re.findall(r"\[\s*(\w+)\s*\]", dims_text)
        members.append((typ, member, dims))
    for member in caps:
        if not any(m == member and not d and t in INTEGERS for t, m, d in members):
            sys.exit(f"{path}: MAX_{member.upper()} names no integer member '{member}'")
    return (package.group(1) if package else ""), name, members, caps


def fingerprint(members):
    v = 0x12345678
    for typ, member, dims in members:
        v = hash_string(v, member)
        v = hash_string(v, typ)  # every member is primitive here
        v = hash_update(v, len(dims))
        for d in dims:
            v = hash_update(v, 0 if d.isdigit() else 1)  # LCM_CONST, LCM_VAR
            v = hash_string(v, d)
    u = v & MASK
    return ((u << 1) + ((u >> 63) & 1)) & MASK


def emit(path, package, name, members, caps, out, index):
    fields = []
    scalars = {}
    for i, (typ, member, dims) in enumerate(members):
        if len(dims) > 3:
            sys.exit(f"{path}: '{member}' has {len(dims)} dimensions; the guard takes up to 3")
        cdims = []
        for d in dims:
            if d.isdigit():
                cdims.append(f"{{{int(d)}, -1}}")
            else:
                if d not in scalars:
                    sys.exit(f"{path}: '{member}' is sized by '{d}', which is not an earlier "
                             "integer member")
                cdims.append(f"{{0, {scalars[d]}}}")
        while len(cdims) < 3:
            cdims.append("{0, -1}")
        if not dims and typ in INTEGERS:
            scalars[member] = i
        cap = f", {caps[member]}" if member in caps else ""
        fields.append(f'    {{"{member}", Prim::{PRIMITIVES[typ]}, {len(dims)}, '
                      f'{{{", ".join(cdims)}}}{cap}}},')
    full = f"{package}.{name}" if package else name
    out.append(f"// {path}")
    out.append(f"const Field kFields{index}[] = {{")
    out.extend(fields)
    out.append("};")
    out.append(f'const Schema kSchema{index} = {{"{full}", 0x{fingerprint(members):016x}ULL, '
               f"kFields{index}, {len(fields)}}};")


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    function, out_path, files = sys.argv[1], sys.argv[2], sys.argv[3:]
    legacy = []
    if "--legacy" in files:
        at = files.index("--legacy")
        files, legacy = files[:at], files[at + 1:]
    out = ["// Generated by cmake/lcm_wire_schema.py from the .lcm files below. Do not edit.",
           '#include "common/wire_guard.h"', "", "namespace ftcal::wire {", "namespace {", ""]
    for i, path in enumerate(sorted(files)):
        emit(path, *parse(path), out, i)
        out.append("")
    out.append("}  // namespace")
    out.append("")
    out.append(f"const std::vector<const Schema*>& {function}() {{")
    refs = ", ".join(f"&kSchema{i}" for i in range(len(files)))
    out.append(f"  static const std::vector<const Schema*> schemas{{{refs}}};")
    out.append("  return schemas;")
    out.append("}")
    out.append("")
    out.append(f"const std::vector<LegacyVersion>& {function}Legacy() {{")
    out.append("  static const std::vector<LegacyVersion> versions{")
    for path in sorted(legacy):
        _, name, members, _ = parse(path)
        out.append(f"      {{0x{fingerprint(members):016x}ULL, {c_string('ftcal.' + name)}, "
                   f"{c_string(legacy_line(path))}}},  // {path}")
    out.append("  };")
    out.append("  return versions;")
    out.append("}")
    out.append("")
    out.append("}  // namespace ftcal::wire")
    text = "\n".join(out) + "\n"
    try:
        if open(out_path, encoding="utf-8").read() == text:
            return
    except OSError:
        pass
    with open(out_path, "w", encoding="utf-8") as f:
        f.write(text)


if __name__ == "__main__":
    main()
