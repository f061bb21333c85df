"""Shared by the benchmark scripts: markdown tables and sections of docs/BENCHMARKS.md."""
import json
import os
import platform
import re
import time
from importlib.metadata import PackageNotFoundError, version

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH_MD = os.path.join(ROOT, 'docs', 'BENCHMARKS.md')
HEADER = ('# Benchmarks\n\nEvery table here is written by a script in `bench/`; rerun it to '
          'refresh its section. Accuracy is always against the simulator\'s ground truth.\n')


def table(headers, rows):
    """Return a markdown table."""
    out = ['| ' + ' | '.join(headers) + ' |', '|' + '|'.join('---' for _ in headers) + '|']
    out += ['| ' + ' | '.join(str(c) for c in r) + ' |' for r in rows]
    return '\n'.join(out)


#: The libraries whose versions can move a figure (requirements.txt pins none of them): the
#: rendering and detection (OpenCV), every array and solve (numpy, scipy).
VERSIONED = ('numpy', 'scipy', 'opencv-python-headless')


def machine():
    """Return one line saying where, and with which libraries, the numbers were measured."""
    libs = []
    for name in VERSIONED:
        try:
            libs.append(f'{name} {version(name)}')
        except PackageNotFoundError:
            pass
    return (f'{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}'
            + ''.join(f', {lib}' for lib in libs) + f', {time.strftime("%Y-%m-%d")}')


def write_section(name, markdown):
    """Replace (or append) the section between <!-- name:start --> and <!-- name:end -->."""
    os.makedirs(os.path.dirname(BENCH_MD), exist_ok=True)
    text = open(BENCH_MD).read() if os.path.exists(BENCH_MD) else HEADER
    block = f'<!-- {name}:start -->\n{markdown.rstrip()}\n<!-- {name}:end -->'
    pat = re.compile(rf'<!-- {re.escape(name)}:start -->.*?<!-- {re.escape(name)}:end -->',
                     re.S)
    text = pat.sub(lambda m: block, text) if pat.search(text) else text.rstrip() + '\n\n' + block
    tmp = BENCH_MD + '.tmp'
    with open(tmp, 'w') as f:
        f.write(text.rstrip() + '\n')
    os.replace(tmp, BENCH_MD)


def write_json(name, data):
    """Write docs/bench/<name>.json."""
    path = os.path.join(ROOT, 'docs', 'bench', name + '.json')
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, 'w') as f:
        json.dump(data, f, indent=1, sort_keys=True)
    return path
