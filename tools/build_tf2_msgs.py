#!/usr/bin/env python3
"""
Build the message package tf2_msgs (TFMessage) with the rosidl generators of the PyPI wheels.

There is no ``ros-jazzy-tf2-msgs`` wheel on PyPI, and the node publishes ``/tf_static`` as
tf2_msgs/msg/TFMessage, as tf2_ros' StaticTransformBroadcaster does.  The interface is one line
(``geometry_msgs/TransformStamped[] transforms``), and the ros-jazzy-* wheels in the venv carry
the generators (rosidl_generator_c/py, rosidl_typesupport_c, _fastrtps_c, _introspection_c),
the C headers (``<venv>/include``) and the libraries (``<venv>/lib``) a message package is
built from; ``make`` runs this once at install time (about a second, with gcc and g++).

Usage, with the venv's Python (the one that has rclpy)::

    <venv>/bin/python tools/build_tf2_msgs.py SITE_PACKAGES [--build-dir DIR]

Result: ``SITE_PACKAGES/tf2_msgs/`` (the Python package and its extension modules) and
``SITE_PACKAGES/ros_tf2_msgs.libs/`` (``libtf2_msgs__rosidl_*.so`` and
``share/tf2_msgs/msg/TFMessage.{msg,idl,json}``); the extension modules find the libraries
through RPATH ``$ORIGIN/../ros_tf2_msgs.libs``, so nothing is needed at run time beyond what
rclpy needs.

Why it is built this way (each found by trying):

- the ``rosidl generate`` command fails in these venvs ("Found duplicate entry point 'py'":
  every generator is installed twice, egg-info and dist-info), so the generators' classes are
  called directly;
- ``libtf2_msgs__rosidl_typesupport_c.so`` dispatches to the concrete type support by
  dlopen() of a bare file name, which fails unless its directory is on LD_LIBRARY_PATH; it is
  therefore linked (DT_NEEDED, RPATH ``$ORIGIN``) against both concrete libraries, which are
  then loaded already when it looks;
- both concrete type supports are needed: with fastrtps_c alone rmw_fastrtps_cpp refuses the
  endpoint ("failed to register type object with incompatible type
  tf2_msgs::msg::dds_::TFMessage_"): it needs introspection_c for the XTypes type object.
"""
import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import sysconfig
import time

PKG = 'tf2_msgs'
MSG_FILES = {'TFMessage.msg': 'geometry_msgs/TransformStamped[] transforms\n'}
DEPS = ['geometry_msgs', 'std_msgs', 'builtin_interfaces']  # transitive interface deps
FULL_TS = ['rosidl_typesupport_fastrtps_c', 'rosidl_typesupport_introspection_c']


VERBOSE = os.environ.get('VERBOSE') == '1'


def run(cmd, **kw):
    """Run a compiler command; print it (whole with VERBOSE=1)."""
    if VERBOSE:
        print('+', ' '.join(str(c) for c in cmd), flush=True)
    else:
        print('+', cmd[0], '...', '-o', cmd[cmd.index('-o') + 1], flush=True)
    subprocess.run([str(c) for c in cmd], check=True, **kw)


def generate(prefix, src, gen, typesupports):
    """Generate the C, type support and Python sources of the package into ``gen``."""
    # rosidl_cli needs ament_index for share/<generator>/resource templates.
    os.environ['AMENT_PREFIX_PATH'] = str(prefix)
    # NB: the `rosidl generate` CLI itself fails in these venvs with
    # "Found duplicate entry point 'py'" (each generator is installed both as an
    # egg-info and a dist-info), so instantiate the CLI extension classes directly.
    from rosidl_generator_c.cli import GenerateC
    from rosidl_generator_py.cli import GeneratePython
    from rosidl_typesupport_c.cli import GenerateCTypesupport
    from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
    from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport

    include_paths = [str(prefix / 'share' / d) for d in DEPS]
    files = [f'{src}:msg/{m}' for m in MSG_FILES]
    jobs = [
        (GenerateC('c'), gen / 'c' / PKG),
        (GenerateCTypesupport('typesupport_c', typesupport_implementations=typesupports),
         gen / 'typesupport_c' / PKG),
        (GenerateFastRTPSCTypesupport('typesupport_fastrtps_c'),
         gen / 'typesupport_fastrtps_c' / PKG),
        (GeneratePython('py', typesupport_implementations=['rosidl_typesupport_c'] + typesupports),
         gen / 'py' / PKG),
    ]
    if 'rosidl_typesupport_introspection_c' in typesupports:
        jobs.append((GenerateIntrospectionCTypesupport('typesupport_introspection_c'),
                     gen / 'typesupport_introspection_c' / PKG))
    for ext, out in jobs:
        ext.generate(PKG, files, include_paths, output_path=out)


def main():
    """Generate, compile and lay out the package; see the module docstring."""
    ap = argparse.ArgumentParser()
    ap.add_argument('output_dir')
    ap.add_argument('--build-dir', default=None)
    a = ap.parse_args()
    t0 = time.time()

    prefix = pathlib.Path(sys.prefix)          # the venv holding the ros-jazzy wheels
    out = pathlib.Path(a.output_dir).resolve()
    build = pathlib.Path(a.build_dir or (out / '_build_tf2_msgs')).resolve()
    typesupports = FULL_TS
    for d in (build,):
        shutil.rmtree(d, ignore_errors=True)
    src = build / 'src' / PKG
    (src / 'msg').mkdir(parents=True)
    for name, text in MSG_FILES.items():
        (src / 'msg' / name).write_text(text)
    gen = build / 'gen'

    generate(prefix, src, gen, typesupports)

    # ---------------- compile ----------------
    inc_root = prefix / 'include'
    if not (inc_root / 'rosidl_runtime_c' / 'rosidl_runtime_c').is_dir():
        sys.exit(f'missing C headers under {inc_root}')
    incs = ['-I', gen / 'c', '-I', gen / 'typesupport_fastrtps_c',
            '-I', gen / 'typesupport_introspection_c', '-I', inc_root]
    for d in sorted(inc_root.iterdir()):
        if d.is_dir():
            incs += ['-I', d]
    py_inc = sysconfig.get_paths()['include']
    import numpy
    np_inc = numpy.get_include()

    libdir = out / 'ros_tf2_msgs.libs'
    pydir = out / PKG
    shutil.rmtree(libdir, ignore_errors=True)
    shutil.rmtree(pydir, ignore_errors=True)
    libdir.mkdir(parents=True)
    pydir.mkdir(parents=True)

    cflags = ['-O2', '-fPIC', '-shared', '-w']
    ldbase = ['-L', libdir, '-L', prefix / 'lib', '-Wl,--no-as-needed', '-Wl,-rpath,$ORIGIN']

    def dep_libs(suffix):
        return [f'-l{d}__{suffix}' for d in DEPS]

    def lib(name, sources, libs, cxx=False, defs=(), extra_inc=()):
        target = libdir / f'lib{PKG}__{name}.so'
        cc = ['g++', '-std=c++17'] if cxx else ['gcc', '-std=c11']
        run(cc + cflags + [f'-D{d}' for d in defs] + incs + list(extra_inc) + sources
            + ['-o', target, f'-Wl,-soname,{target.name}'] + ldbase + libs)
        return target

    gc = gen / 'c' / PKG / 'msg' / 'detail'
    lib('rosidl_generator_c', sorted(gc.glob('*.c')),
        dep_libs('rosidl_generator_c') + ['-lrosidl_runtime_c', '-lrcutils'],
        defs=[f'ROSIDL_GENERATOR_C_BUILDING_DLL_{PKG}'])

    lib('rosidl_typesupport_fastrtps_c',
        sorted((gen / 'typesupport_fastrtps_c' / PKG / 'msg' / 'detail').glob('*.cpp')),
        [f'-l{PKG}__rosidl_generator_c'] + dep_libs('rosidl_typesupport_fastrtps_c')
        + dep_libs('rosidl_generator_c')
        + ['-lrosidl_typesupport_fastrtps_c', '-lrosidl_typesupport_fastrtps_cpp',
           '-lfastcdr', '-lrmw', '-lrosidl_dynamic_typesupport', '-lrosidl_runtime_c',
           '-lrcutils'],
        cxx=True, defs=[f'ROSIDL_TYPESUPPORT_FASTRTPS_C_BUILDING_DLL_{PKG}'])

    if 'rosidl_typesupport_introspection_c' in typesupports:
        lib('rosidl_typesupport_introspection_c',
            sorted((gen / 'typesupport_introspection_c' / PKG / 'msg' / 'detail').glob('*.c')),
            [f'-l{PKG}__rosidl_generator_c'] + dep_libs('rosidl_typesupport_introspection_c')
            + dep_libs('rosidl_generator_c')
            + ['-lrosidl_typesupport_introspection_c', '-lrosidl_runtime_c', '-lrcutils'],
            defs=[f'ROSIDL_TYPESUPPORT_INTROSPECTION_C_BUILDING_DLL_{PKG}'])

    # Link the concrete typesupport libs into the rosidl_typesupport_c lib (DT_NEEDED, found via
    # RPATH $ORIGIN).  In the dispatch case this pre-loads them, so the dispatch's
    # dlopen("libtf2_msgs__rosidl_typesupport_<ts>.so") (bare name, which fails unless the
    # directory is on LD_LIBRARY_PATH) is satisfied by the already-loaded object (same SONAME).
    ts_link = [f'-l{PKG}__{ts}' for ts in typesupports]
    lib('rosidl_typesupport_c',
        sorted((gen / 'typesupport_c' / PKG / 'msg').glob('*.cpp')),
        [f'-l{PKG}__rosidl_generator_c'] + ts_link + dep_libs('rosidl_typesupport_c')
        + dep_libs('rosidl_generator_c')
        + ['-lrosidl_typesupport_c', '-lrosidl_runtime_c', '-lrcutils'],
        cxx=True, defs=['ROSIDL_TYPESUPPORT_C_BUILDING_DLL'])

    gp = gen / 'py' / PKG
    # Python symbols are resolved from the interpreter (like the wheel's libs: no -lpython).
    lib('rosidl_generator_py', sorted((gp / 'msg').glob('*_s.c')),
        [f'-l{PKG}__rosidl_generator_c', f'-l{PKG}__rosidl_typesupport_c']
        + dep_libs('rosidl_generator_py') + dep_libs('rosidl_generator_c')
        + dep_libs('rosidl_typesupport_c')
        + ['-lrosidl_runtime_c', '-lrosidl_typesupport_c', '-lrcutils'],
        extra_inc=['-I', py_inc, '-I', np_inc])

    # python extension modules: <pkg>/<pkg>_s__<typesupport>.so
    ext_suffix = sysconfig.get_config_var('EXT_SUFFIX')
    for ts in ['rosidl_typesupport_c'] + typesupports:
        ep = gp / f'_{PKG}_s.ep.{ts}.c'
        target = pydir / f'{PKG}_s__{ts}{ext_suffix}'
        run(['gcc', '-std=c11'] + cflags + incs
            + ['-I', py_inc, ep, '-o', target, '-L', libdir, '-L', prefix / 'lib',
               '-Wl,--no-as-needed', '-Wl,-rpath,$ORIGIN/../ros_tf2_msgs.libs',
               f'-l{PKG}__rosidl_generator_py', f'-l{PKG}__{ts}',
               f'-l{PKG}__rosidl_generator_c', '-lrosidl_runtime_c', '-lrcutils']
            + (['-lrosidl_typesupport_c'] if ts == 'rosidl_typesupport_c' else []))

    # python sources
    (pydir / '__init__.py').write_text('')
    (pydir / 'msg').mkdir()
    for f in (gp / 'msg').glob('*.py'):
        shutil.copy2(f, pydir / 'msg' / f.name)
    # interface files (what share/<pkg>/msg holds in a ROS install)
    share = libdir / 'share' / PKG / 'msg'
    share.mkdir(parents=True)
    for f in (list((src / 'msg').glob('*.msg'))
              + list((gen / 'c' / PKG / 'tmp' / 'msg').glob('*.idl'))
              + list((gen / 'c' / PKG / 'msg').glob('*.json'))):
        shutil.copy2(f, share / f.name)
    print(f'built {PKG} into {out} in {time.time() - t0:.1f}s')


if __name__ == '__main__':
    main()
