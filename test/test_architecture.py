"""The package's layers (docs/ARCHITECTURE.md): no module imports one above it, no cycles."""

import ast
import os

import pytest

PKG = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'armcal_ros')

#: Layer of each top-level part of the package; a module may import its own layer or below.
LAYERS = {
    'cli': 6, 'demo': 6, 'ros': 6,
    'offline': 5, 'compare': 5,
    'compose': 4,
    'settings': 3, 'params': 3,
    'engine': 2, 'change_tracking': 2, 'stamp_latency': 2, 'solver_process': 2,
    'frontend': 1,
    'core': 0, 'robot': 0, 'io': 0, 'sim': 0,
}
#: Within the foundations, what each part may import besides itself.
FOUNDATIONS = {'core': set(), 'robot': {'core'}, 'io': {'core'}, 'sim': {'core', 'robot', 'io'}}


def _modules():
    out = {}
    for root, _, files in os.walk(PKG):
        for f in files:
            if f.endswith('.py'):
                path = os.path.join(root, f)
                rel = os.path.relpath(path, os.path.dirname(PKG))[:-3].replace(os.sep, '.')
                out[rel[:-len('.__init__')] if rel.endswith('.__init__') else rel] = path
    return out


def _imports(name, path, known):
    """Return {imported armcal_ros module: line} of a module, nested imports included."""
    with open(path) as f:
        tree = ast.parse(f.read(), path)
    package = name if path.endswith('__init__.py') else name.rpartition('.')[0]
    found = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parts = package.split('.')
                base = '.'.join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            targets = [f'{base}.{a.name}' if f'{base}.{a.name}' in known else base
                       for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:
                t = t.rpartition('.')[0]
            if t and t != name and t.startswith('armcal_ros'):
                found.setdefault(t, node.lineno)
    return found


MODULES = _modules()
GRAPH = {m: _imports(m, p, MODULES) for m, p in MODULES.items()}


def _part(module):
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else 'armcal_ros'


def test_every_part_has_a_layer():
    assert sorted({_part(m) for m in MODULES} - set(LAYERS) - {'armcal_ros'}) == []


@pytest.mark.parametrize('module', sorted(MODULES))
def test_no_module_imports_one_above_it(module):
    part = _part(module)
    if part == 'armcal_ros':
        return
    bad = []
    for target, line in GRAPH[module].items():
        other = _part(target)
        if other == 'armcal_ros':
            continue
        if LAYERS[other] > LAYERS[part]:
            bad.append(f'line {line}: {target} ({other} is above {part})')
        elif part in FOUNDATIONS and other in FOUNDATIONS and other != part and \
                other not in FOUNDATIONS[part]:
            bad.append(f'line {line}: {target} ({part} may not import {other})')
    assert not bad, f'{module}: ' + '; '.join(bad)


def test_no_import_cycles():
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 'open'
        stack.append(m)
        for t in GRAPH[m]:
            if state.get(t) == 'open':
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 'done'
    for m in sorted(GRAPH):
        if m not in state:
            visit(m)
    assert not cycles, ' ; '.join(' -> '.join(c) for c in cycles)


def test_the_checker_sees_a_violation():
    # A cycle and an upward import, made up, must be found by the same rules.
    assert 'armcal_ros.core.camera' in GRAPH['armcal_ros.core.adjustment']
    assert LAYERS[_part('armcal_ros.compose')] > LAYERS[_part('armcal_ros.engine')]
