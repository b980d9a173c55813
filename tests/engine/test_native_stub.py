"""The native module's type stub (native/_native/*.pyi) against the built module: every
public name of either is in the other, classes member by member (methods, properties and
whether they can be set, base classes), functions argument by argument (the names
pybind11 bound, positional-only where it calls them arg0, arg1..., defaults where it has
them), the falcon submodule likewise. The stub is written by hand; this keeps it true to
native/binding/*.cpp as they change."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from types import ModuleType, WrapperDescriptorType

import pytest
from clothball import _native

STUBS = Path(__file__).resolve().parents[2] / "native" / "_native"
UNNAMED = re.compile(r"arg\d+")  # pybind11's name for an argument bound without py::arg


def public(name: str) -> bool:
    return not name.startswith("_") or name == "__init__"


def stub_params(fn: ast.FunctionDef, method: bool) -> list[tuple[str, bool, bool]]:
    """(name, positional-only, has a default) of each of the stub function's arguments."""
    a = fn.args
    assert not (a.vararg or a.kwarg or a.kwonlyargs), f"{fn.name}: only plain arguments"
    named = [(p.arg, True) for p in a.posonlyargs] + [(p.arg, False) for p in a.args]
    first_default = len(named) - len(a.defaults)
    out = [(n, po, k >= first_default) for k, (n, po) in enumerate(named)]
    return out[1:] if method else out


def split_top(text: str) -> list[str]:
    """`text` split at its commas outside brackets (a default such as [0.0, 0.0, 0.08])."""
    parts, depth, start = [], 0, 0
    for k, ch in enumerate(text):
        depth += ch in "([{<"
        depth -= ch in ")]}>"
        if ch == "," and depth == 0:
            parts.append(text[start:k])
            start = k + 1
    return [p.strip() for p in [*parts, text[start:]] if p.strip()]


def runtime_params(fn: object, method: bool) -> list[tuple[str, bool]]:
    """(name, has a default) of each argument, from the signature pybind11 writes as the
    first line of the docstring (its functions have no inspect.signature)."""
    line = (getattr(fn, "__doc__", None) or "").splitlines()[0]
    m = re.fullmatch(r"\w+\((.*)\) -> .*", line)
    assert m, f"not a pybind11 signature: {line!r}"
    out = [(p.split(":")[0].strip(), " = " in p) for p in split_top(m.group(1))]
    return out[1:] if method else out


def check_function(where: str, fn: object, stub: ast.FunctionDef, method: bool) -> list[str]:
    got, want = runtime_params(fn, method), stub_params(stub, method)
    if len(got) != len(want):
        return [f"{where}: {len(got)} arguments bound, {len(want)} in the stub"]
    errors = []
    for (name, default), (s_name, s_posonly, s_default) in zip(got, want, strict=True):
        if UNNAMED.fullmatch(name):
            if not s_posonly:
                errors.append(f"{where}: {name} (bound without py::arg) is {s_name!r} in the "
                              "stub, not positional-only")
        elif s_posonly or name != s_name:
            errors.append(f"{where}: argument {name!r} is {s_name!r} in the stub"
                          + (", positional-only" if s_posonly else ""))
        if default != s_default:
            errors.append(f"{where}: argument {name!r}: a default in only one of the two")
    return errors


def decorators(fn: ast.FunctionDef) -> set[str]:
    return {ast.unparse(d) for d in fn.decorator_list}


KINDS = {"method": "a method", "attribute": "a settable attribute",
         "readonly": "a read-only property"}


def stub_members(cls: ast.ClassDef) -> dict[str, tuple[str, ast.FunctionDef | None]]:
    """Each member's kind (one of KINDS) and, for a method, its def."""
    out: dict[str, tuple[str, ast.FunctionDef | None]] = {}
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            out[node.target.id] = ("attribute", None)
        elif isinstance(node, ast.FunctionDef):
            deco = decorators(node)
            if "property" in deco:
                out[node.name] = ("readonly", None)
            elif f"{node.name}.setter" in deco:
                out[node.name] = ("attribute", None)
            else:
                out[node.name] = ("method", node)
    return out


def check_class(where: str, cls: type, stub: ast.ClassDef) -> list[str]:
    errors = []
    bases = [b.__name__ for b in cls.__bases__ if b.__name__ != "pybind11_object"]
    if bases != [ast.unparse(b) for b in stub.bases]:
        errors.append(f"{where}: bases {bases}, in the stub {[ast.unparse(b) for b in stub.bases]}")
    members = stub_members(stub)
    # A slot wrapper is no binding: the __init__ of a class bound without a constructor
    # (it raises TypeError), which the stub leaves out.
    bound = {n: v for n, v in vars(cls).items()
             if public(n) and not isinstance(v, WrapperDescriptorType)}
    for name in sorted(bound.keys() - members.keys()):
        errors.append(f"{where}.{name}: bound, not in the stub")
    for name in sorted(members.keys() - bound.keys()):
        errors.append(f"{where}.{name}: in the stub, not bound")
    for name in sorted(bound.keys() & members.keys()):
        value, (kind, fn) = bound[name], members[name]
        if isinstance(value, property):
            want = "attribute" if value.fset is not None else "readonly"
            if kind != want:
                errors.append(f"{where}.{name}: bound as {KINDS[want]}, {KINDS[kind]} in "
                              "the stub")
        elif kind != "method" or fn is None:
            errors.append(f"{where}.{name}: bound as a method, {KINDS[kind]} in the stub")
        else:
            errors += check_function(f"{where}.{name}", value, fn, method=True)
    return errors


def check_module(where: str, module: ModuleType, stub_file: Path) -> list[str]:
    tree = ast.parse(stub_file.read_text(), str(stub_file))
    declared: dict[str, ast.stmt] = {}
    submodules: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.ClassDef | ast.FunctionDef):
            declared[node.name] = node
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            declared[node.target.id] = node
        elif isinstance(node, ast.ImportFrom) and node.module is None:  # from . import x as x
            submodules |= {a.asname or a.name for a in node.names}
    declared = {n: v for n, v in declared.items() if public(n)}
    exported = {n: v for n, v in vars(module).items() if public(n)}
    errors = [f"{where}.{n}: exported, not in the stub"
              for n in sorted(exported.keys() - declared.keys() - submodules)]
    errors += [f"{where}.{n}: in the stub, not exported"
               for n in sorted((declared.keys() | submodules) - exported.keys())]
    for name in sorted(exported.keys() & (declared.keys() | submodules)):
        value, here = exported[name], f"{where}.{name}"
        node = declared.get(name)
        if isinstance(value, ModuleType):
            sub = stub_file.parent / f"{name}.pyi"
            if name not in submodules or not sub.is_file():
                errors.append(f"{here}: a submodule; the stub needs {sub.name} and an import")
            else:
                errors += check_module(here, value, sub)
        elif isinstance(value, type):
            if not isinstance(node, ast.ClassDef):
                errors.append(f"{here}: a class, not one in the stub")
            else:
                errors += check_class(here, value, node)
        elif callable(value):
            if not isinstance(node, ast.FunctionDef):
                errors.append(f"{here}: a function, not one in the stub")
            else:
                errors += check_function(here, value, node, method=False)
        elif not isinstance(node, ast.AnnAssign):
            errors.append(f"{here}: a value, not an annotated name in the stub")
        else:
            # int, float, str, dict[...]: the annotation names the value's type
            ann = node.annotation
            typename = ast.unparse(ann.value if isinstance(ann, ast.Subscript) else ann)
            if typename != type(value).__name__:
                errors.append(f"{here}: {type(value).__name__} when built, {typename} in "
                              "the stub")
    return errors


def test_the_stub_declares_what_the_module_exports_and_nothing_else() -> None:
    errors = check_module("_native", _native, STUBS / "__init__.pyi")
    assert not errors, "native/_native/*.pyi is out of step with the bindings:\n" + "\n".join(
        errors)


def test_the_checks_see_a_drift() -> None:
    """The comparison itself: a missing name, a renamed argument and a lost default in a
    stub are each reported (else the test above could pass by checking nothing)."""
    stub = ast.parse("class Engine:\n"
                     "    def __init__(self, backend: str, double_precision: bool) -> None: ...\n"
                     "def cuda_copy_bandwidth_gbs(size: int, reps: int) -> float: ...\n")
    cls, fn = stub.body
    assert isinstance(cls, ast.ClassDef) and isinstance(fn, ast.FunctionDef)
    class_errors = check_class("_native.Engine", _native.Engine, cls)
    assert "_native.Engine.step: bound, not in the stub" in class_errors
    assert any("__init__: 3 arguments bound, 2" in e for e in class_errors)
    fn_errors = check_function("f", _native.cuda_copy_bandwidth_gbs, fn, method=False)
    assert fn_errors == ["f: argument 'bytes' is 'size' in the stub",
                         "f: argument 'reps': a default in only one of the two"]


@pytest.mark.parametrize("text, parts", [
    ("a: int, b: list[float] = [0.0, 0.0, 0.08], c: x = <C object at 0x1>",
     ["a: int", "b: list[float] = [0.0, 0.0, 0.08]", "c: x = <C object at 0x1>"]),
    ("", []),
])
def test_split_top(text: str, parts: list[str]) -> None:
    assert split_top(text) == parts
