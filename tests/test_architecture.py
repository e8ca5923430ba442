"""The house's architecture, read from the sources (no build, no device): the Rust core's files
import each other without circles, only downward through the layers, each folder in the order its
`mod.rs` declares its files, and no two files share a name.

The graph is built file by file from what each file names: `use crate::…`, `use super::…` and
`use self::…` statements, `crate::…`/`super::…` paths written inline, and `mod` declarations (a
folder's `mod.rs` points at the files it declares). A path through a folder's `mod.rs` or `lib.rs`
(a facade's `pub use`) counts as an import of the file that defines the name; a path through any
other file counts as an import of that file.

The checks (`cycles`, `upward_imports`, `out_of_order`, `duplicate_names`) take a plain graph
(file -> files it imports), so that the same checks can run over python/vkray's modules."""

from __future__ import annotations

import pathlib
import re
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Set, Tuple

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SRC = ROOT / "src"

Graph = Dict[str, Set[str]]

# The Rust core's layers, lowest first: a file imports only files of its own layer or lower ones.
# `error.rs` is the ground under the ground: every layer returns its errors. `lib.rs` is the root:
# it declares (and re-exports from) every layer.
RUST_LAYERS: Dict[str, int] = {"error": 0, "geometry": 1, "gpu": 2, "embree": 2, "scene": 3, "trace": 4, "python": 5}


# ---------------------------------------------------------------- checks over any graph


def cycles(graph: Graph) -> List[List[str]]:
    """The graph's circles: each strongly connected component of two or more nodes (or a node that
    imports itself), sorted (Tarjan's algorithm, iterative)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    on_stack: Set[str] = set()
    stack: List[str] = []
    found: List[List[str]] = []
    counter = 0
    nodes = sorted(set(graph) | {t for targets in graph.values() for t in targets})
    for root in nodes:
        if root in index:
            continue
        work: List[Tuple[str, Iterable[str]]] = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1 or node in graph.get(node, ()):
                        found.append(sorted(component))
    return sorted(found)


def upward_imports(graph: Graph, layer_of: Callable[[str], int]) -> List[Tuple[str, str]]:
    """Every import of a file in a higher layer than the importer's."""
    return sorted((a, b) for a, targets in graph.items() for b in targets if layer_of(b) > layer_of(a))


def out_of_order(graph: Graph, order: Sequence[str]) -> List[Tuple[str, str]]:
    """Imports between two nodes of `order` (one folder's files, lowest first) that run from a file
    to one declared after it."""
    rank = {node: i for i, node in enumerate(order)}
    return sorted(
        (a, b) for a, targets in graph.items() for b in targets if a in rank and b in rank and rank[b] > rank[a]
    )


def duplicate_names(paths: Iterable[str], ignore: Iterable[str] = ()) -> Dict[str, List[str]]:
    """File names that occur more than once (`ignore`: names every folder has, like mod.rs)."""
    by_name: Dict[str, List[str]] = {}
    for path in paths:
        name = pathlib.PurePosixPath(path).name
        if name not in set(ignore):
            by_name.setdefault(name, []).append(path)
    return {name: sorted(found) for name, found in sorted(by_name.items()) if len(found) > 1}


# ---------------------------------------------------------------- reading the Rust sources

_TOKEN = re.compile(
    r"""//[^\n]*                       # line comment
      | /\*                            # block comment (nesting handled below)
      | r(\#*)"                        # raw string
      | b?"(?:\\.|[^"\\])*"            # string
      | b?'(?:\\(?:x[0-9a-fA-F]{2}|u\{[0-9a-fA-F]+\}|.)|[^\\'\n])'  # char (not a lifetime)
    """,
    re.VERBOSE | re.DOTALL,
)


def strip_rust(text: str) -> str:
    """The code without comments, strings or chars (each replaced by spaces, so offsets hold)."""
    out: List[str] = []
    pos = 0
    while True:
        match = _TOKEN.search(text, pos)
        if match is None:
            out.append(text[pos:])
            return "".join(out)
        out.append(text[pos : match.start()])
        token = match.group(0)
        end = match.end()
        if token == "/*":
            depth = 1
            while depth and end < len(text):
                if text.startswith("/*", end):
                    depth, end = depth + 1, end + 2
                elif text.startswith("*/", end):
                    depth, end = depth - 1, end + 2
                else:
                    end += 1
        elif match.group(1) is not None:
            closing = '"' + match.group(1)
            found = text.find(closing, end)
            end = len(text) if found < 0 else found + len(closing)
        out.append(re.sub(r"[^\n]", " ", text[match.start() : end]))
        pos = end


def expand_use_tree(tree: str) -> List[Tuple[List[str], str]]:
    """`a::b::{c, d::{e as f, self}}` -> [(['a','b','c'], 'c'), (['a','b','d','e'], 'f'), (['a','b','d'], 'd')]:
    each imported path with the name it is bound to."""
    tree = re.sub(r"\s+", "", re.sub(r"\s+as\s+", "@", tree)).lstrip(":")
    depth = 0
    for i, ch in enumerate(tree):
        if ch == "{":
            if depth == 0:
                prefix = [s for s in tree[:i].split("::") if s]
                inner, items, start, d = tree[i + 1 : tree.rindex("}")], [], 0, 0
                for j, c in enumerate(inner):
                    d += c == "{"
                    d -= c == "}"
                    if c == "," and d == 0:
                        items.append(inner[start:j])
                        start = j + 1
                items.append(inner[start:])
                result = []
                for item in filter(None, items):
                    for path, name in expand_use_tree(item):
                        if path == ["self"]:
                            result.append((prefix, prefix[-1]))
                        else:
                            result.append((prefix + path, name))
                return result
            depth += 1
    path, _, alias = tree.partition("@")
    segments = [s for s in path.split("::") if s]
    return [(segments, alias or segments[-1])] if segments else []


class RustFile:
    """One source file: its module path, its inline modules, its `use`s, inline paths and `mod`s."""

    def __init__(self, path: pathlib.Path, src: pathlib.Path) -> None:
        self.rel = path.relative_to(src).as_posix()
        parts = list(path.relative_to(src).with_suffix("").parts)
        self.facade = parts[-1] in ("mod", "lib")
        self.module = tuple(parts[:-1] if self.facade else parts)
        self.code = strip_rust(path.read_text())
        # Inline `mod name { … }` blocks: (start, end, name).
        self.inline: List[Tuple[int, int, str]] = []
        for match in re.finditer(r"\bmod\s+(\w+)\s*\{", self.code):
            depth, i = 1, match.end()
            while depth and i < len(self.code):
                depth += {"{": 1, "}": -1}.get(self.code[i], 0)
                i += 1
            self.inline.append((match.start(), i, match.group(1)))
        declared = re.finditer(r"^\s*(?:pub(?:\([\w:\s]+\))?\s+)?mod\s+(\w+)\s*;", self.code, re.M)
        self.mods = [m.group(1) for m in declared]
        self.uses: List[Tuple[int, List[str], str, bool]] = []  # (offset, path, bound name, pub)
        spans = []
        for match in re.finditer(r"(\bpub(?:\([\w:\s]+\))?\s+)?\buse\s+([^;]+);", self.code):
            spans.append((match.start(), match.end()))
            for path, name in expand_use_tree(match.group(2)):
                self.uses.append((match.start(), path, name, match.group(1) is not None))
        self.paths: List[Tuple[int, List[str]]] = []
        for match in re.finditer(r"(?<![\w:])(?:crate|super|self)(?:\s*::\s*\w+)+", self.code):
            if not any(a <= match.start() < b for a, b in spans):
                self.paths.append((match.start(), re.sub(r"\s+", "", match.group(0)).split("::")))

    def module_at(self, offset: int) -> Tuple[str, ...]:
        inner = [name for start, end, name in sorted(self.inline) if start <= offset < end]
        return self.module + tuple(inner)


def rust_files(src: pathlib.Path = SRC) -> Dict[Tuple[str, ...], RustFile]:
    files = [RustFile(p, src) for p in sorted(src.rglob("*.rs"))]
    return {f.module: f for f in files}


def rust_graph(src: pathlib.Path = SRC) -> Graph:
    """File -> the files it imports (paths relative to `src`)."""
    files = rust_files(src)

    def absolute(module: Tuple[str, ...], path: List[str], in_use: bool) -> Optional[List[str]]:
        head, rest = path[0], path[1:]
        if head == "crate":
            return rest
        if head in ("super", "self"):
            base = list(module)
            while path and path[0] in ("super", "self"):
                if path[0] == "super":
                    base = base[:-1]
                path = path[1:]
            return base + path
        if in_use and tuple(module) + (head,) in files:
            return list(module) + path  # a child module named without `self::`
        return None  # another crate (std, ash, …)

    def resolve(segments: List[str], seen: int = 0) -> Optional[RustFile]:
        for k in range(len(segments), -1, -1):
            owner = files.get(tuple(segments[:k]))
            if owner is None:
                continue
            rest = segments[k:]
            if owner.facade and rest and seen < 16:
                for offset, path, name, public in owner.uses:
                    if public and name == rest[0]:
                        target = absolute(owner.module_at(offset), path, True)
                        if target is not None:
                            found = resolve(target + rest[1:], seen + 1)
                            if found is not None:
                                return found
            return owner
        return None

    graph: Graph = {}
    for file in files.values():
        targets = graph.setdefault(file.rel, set())
        for name in file.mods:
            child = files.get(file.module + (name,))
            if child is not None:
                targets.add(child.rel)
        named = [(o, p, True) for o, p, _, _ in file.uses] + [(o, p, False) for o, p in file.paths]
        for offset, path, in_use in named:
            segments = absolute(file.module_at(offset), path, in_use)
            target = resolve(segments) if segments is not None else None
            if target is not None and target.rel != file.rel:
                targets.add(target.rel)
    return graph


def rust_layer(rel: str) -> int:
    """A file's layer: its folder's (or, at the top, its own name's); lib.rs is above them all."""
    top = rel.split("/")[0].removesuffix(".rs")
    return RUST_LAYERS.get(top, max(RUST_LAYERS.values()) + 1)


def folder_orders(src: pathlib.Path = SRC) -> Dict[str, List[str]]:
    """Each folder's files, lowest first: in the order its `mod.rs` declares them."""
    orders = {}
    for file in rust_files(src).values():
        if file.facade and file.rel != "lib.rs":
            folder = file.rel.rsplit("/", 1)[0]
            orders[folder] = [f"{folder}/{name}.rs" for name in file.mods]
    return orders


# ---------------------------------------------------------------- the tests


def test_the_reader_sees_imports():
    """The reader finds what it must (a check that cannot pass on an empty graph)."""
    graph = rust_graph()
    assert "lib.rs" in graph and len(graph) > 30
    assert sum(len(t) for t in graph.values()) > 100
    expected = [(["a", "b", "c"], "d"), (["a", "b"], "b"), (["a", "e"], "e")]
    assert expand_use_tree("a::{b::{c as d, self}, e}") == expected
    toy = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(toy) == [["a", "b", "c"]]
    assert upward_imports(toy, lambda n: {"a": 0, "b": 0, "c": 1, "d": 2}[n]) == [("b", "c")]
    assert out_of_order(toy, ["a", "b", "c"]) == [("a", "b"), ("b", "c")]


def test_rust_files_import_without_cycles():
    assert cycles(rust_graph()) == []


def test_rust_layers_import_only_downward():
    assert upward_imports(rust_graph(), rust_layer) == []


@pytest.mark.parametrize("folder", sorted(folder_orders()))
def test_rust_folder_files_import_in_declared_order(folder):
    """Inside a folder, a file imports only files its mod.rs declares before it."""
    assert out_of_order(rust_graph(), folder_orders()[folder]) == []


def test_rust_file_names_are_unique():
    assert duplicate_names((f.rel for f in rust_files().values()), ignore=["mod.rs"]) == {}


def test_every_rust_file_says_its_job():
    missing = [f.rel for f in rust_files().values() if not (SRC / f.rel).read_text().lstrip().startswith("//!")]
    assert missing == []


# ---------------------------------------------------------------- the Python layer (python/vkray)

PYTHON = ROOT / "python" / "vkray"

# python/vkray's modules, lowest first: a module imports only modules before it (imports under
# TYPE_CHECKING and inside functions count too). `vkray` is the package's __init__; the modules
# after it are the optional front ends, which use the package's public names.
PYTHON_ORDER: List[str] = [
    "_core",
    "_arrays",
    "_progress",
    "data",
    "sensors",
    "_options",
    "_pictures",
    "_results",
    "_queries",
    "_secondary",
    "_device",
    "_device_group",
    "_preview",
    "vkray",
    "_cli",
    "__main__",
    "dask",
    "trimesh",
    "open3d",
]


def python_modules(root: pathlib.Path = PYTHON) -> Dict[str, pathlib.Path]:
    """python/vkray's modules by name (a package by its folder's name; vkray's own __init__ is
    "vkray")."""
    modules: Dict[str, pathlib.Path] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        name = rel.parent.as_posix() if rel.name == "__init__.py" else rel.with_suffix("").as_posix()
        modules["vkray" if name == "." else name.replace("/", ".")] = path
    return modules


def _is_python_module(name: str) -> bool:
    """Whether vkray has a module (a .py file, the core's stub, or a package) of this name."""
    return any((PYTHON / f"{name}{suffix}").exists() for suffix in (".py", ".pyi")) or (PYTHON / name).is_dir()


def python_imports(path: pathlib.Path, package: str) -> List[Tuple[str, List[str]]]:
    """(module imported, names taken from it) of every import in a module of ``package`` (the
    module's own package, relative to vkray: "" at the top), at any depth."""
    import ast

    found: List[Tuple[str, List[str]]] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            parts = [p for p in package.split(".") if p][: max(0, len(package.split(".")) - (node.level - 1))]
            base = ".".join(parts + ([node.module] if node.module else []))
            names = [alias.name for alias in node.names]
            if base:
                found.append((base, names))
            else:  # `from . import x`: a module of vkray, or a name of its __init__
                found.extend((name, []) if _is_python_module(name) else ("vkray", [name]) for name in names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "vkray":
            rest = node.module.split(".", 1)
            found.append((rest[1] if len(rest) > 1 else "vkray", [alias.name for alias in node.names]))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "vkray":
                    rest = alias.name.split(".", 1)
                    found.append((rest[1] if len(rest) > 1 else "vkray", []))
    return found


def python_graph(root: pathlib.Path = PYTHON) -> Graph:
    """Module -> the vkray modules it imports (an import of a submodule of `data` counts as `data`)."""
    graph: Graph = {}
    for name, path in python_modules(root).items():
        package = name if path.name == "__init__.py" and name != "vkray" else name.rpartition(".")[0]
        targets = {target.split(".")[0] for target, _ in python_imports(path, package)}
        graph[name.split(".")[0]] = graph.get(name.split(".")[0], set()) | (targets - {name.split(".")[0]})
    return graph


def test_the_python_reader_sees_imports():
    graph = python_graph()
    assert {"_device", "_queries", "_results", "vkray", "dask", "trimesh"} <= set(graph)
    assert {"_queries", "_results", "_options"} <= graph["_device"]
    assert "vkray" in graph["trimesh"] and "_device" in graph["vkray"]


def test_python_modules_import_without_cycles():
    assert cycles(python_graph()) == []


def test_python_modules_import_only_downward():
    """Each module imports only modules listed before it in PYTHON_ORDER (which lists them all)."""
    graph = python_graph()
    assert sorted(set(graph) - set(PYTHON_ORDER)) == []
    assert out_of_order(graph, PYTHON_ORDER) == []


def test_no_python_module_reaches_another_modules_private_names():
    """`from .x import _name` (or `vkray._x._name`) of another module's private name: none. The
    private modules' public names (`_device.Scene`) are the house's internal interfaces."""
    reaches = []
    for name, path in python_modules().items():
        package = name if path.name == "__init__.py" and name != "vkray" else name.rpartition(".")[0]
        for target, names in python_imports(path, package):
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            reaches += [f"{name}: {target}.{n}" for n in private if target != "_core"]
        text = path.read_text()
        reaches += [f"{name}: {m.group(0)}" for m in re.finditer(r"\b(?:vkray\.)?_[a-z_]+\._[a-z][A-Za-z_]*\b", text)
                    if not m.group(0).startswith("_core.")]
    assert reaches == []
