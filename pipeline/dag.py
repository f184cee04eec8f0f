"""Stage graph: topological order and the upstream closure of a target."""

from __future__ import annotations

from graphlib import CycleError, TopologicalSorter

from pipeline.errors import ConfigError


def topological_order(needs: dict[str, list[str]]) -> list[str]:
    """All stages, dependencies first; ties keep declaration order so runs are predictable."""
    order_index = {name: i for i, name in enumerate(needs)}
    sorter = TopologicalSorter({name: deps for name, deps in needs.items()})
    try:
        sorter.prepare()
    except CycleError as exc:
        cycle = " -> ".join(exc.args[1])
        raise ConfigError(f"stages form a cycle: {cycle}") from None
    order: list[str] = []
    while sorter.is_active():
        ready = sorted(sorter.get_ready(), key=order_index.__getitem__)
        order.extend(ready)
        sorter.done(*ready)
    return order


def upstream_closure(needs: dict[str, list[str]], targets: list[str]) -> list[str]:
    """The targets and everything they depend on, in topological order."""
    for t in targets:
        if t not in needs:
            raise ConfigError(f"unknown stage '{t}' (stages: {', '.join(needs)})")
    keep: set[str] = set()
    stack = list(targets)
    while stack:
        name = stack.pop()
        if name not in keep:
            keep.add(name)
            stack.extend(needs[name])
    return [s for s in topological_order(needs) if s in keep]
