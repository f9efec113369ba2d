"""Import cycles among the project's modules, packages included (``lint-imports`` checks only the layers):

    python -m tools.import_cycles

Builds the import graph with grimp (what import-linter uses), imports under ``TYPE_CHECKING`` included (a
type-only cycle is a cycle too), and prints each strongly connected set of more than one module (and each
module importing itself); exit status 1 when there is one.  A package's ``__init__`` counts as the package's
module, so a submodule that imports its own package's ``__init__`` which imports it back is a cycle too.
"""
from __future__ import annotations

import sys
from pathlib import Path

import grimp

PACKAGES = ("base", "data", "models", "scene", "tasks", "motion")


def cycles(graph) -> list[list[str]]:
    """Strongly connected sets of more than one module (Tarjan's algorithm, iterative), sorted."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []
    counter = 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.append(member)
                    if member == node:
                        break
                if len(group) > 1 or node in graph.find_modules_directly_imported_by(node):
                    out.append(sorted(group))
    return sorted(out)


def project_graph():
    """grimp's import graph of the packages, ``TYPE_CHECKING`` imports included."""
    root = str(Path(__file__).resolve().parents[1])
    if root not in sys.path:
        sys.path.insert(0, root)
    return grimp.build_graph(*PACKAGES, include_external_packages=False, exclude_type_checking_imports=False,
                             cache_dir=None)


def main() -> int:
    graph = project_graph()
    found = cycles(graph)
    for group in found:
        print("cycle: " + " <-> ".join(group))
    print(f"{len(graph.modules)} modules, {len(found)} import cycle(s)")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
