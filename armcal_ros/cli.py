"""
The ``armcal`` command: calibrate, replay, simulate and demo (README, "Command line").

Each subcommand is a pair of functions registered in :data:`SUBCOMMANDS`: one adds its
arguments to an argparse sub-parser, the other runs it and returns the exit status.  Errors a
user can fix end the command with a one-line reason on stderr and a non-zero status.
"""

import argparse
import math
import sys

from armcal_ros.params import number_arg
from armcal_ros.ros.replay import add_arguments as _add_replay, run as _run_replay


# ---- simulate ---------------------------------------------------------------------------

def _add_simulate(p):
    from armcal_ros.sim.cell import SCENARIOS
    p.add_argument('--output', required=True, metavar='BAG',
                   help='bag directory to create (must not exist); ground truth goes to '
                        'BAG/ground_truth/')
    from armcal_ros.sim.cells import CELLS
    from armcal_ros.sim.true_robot import ERROR_MODELS
    p.add_argument('--cell', default='puma-3cam', choices=sorted(CELLS),
                   help='arm, cameras and image transport: ' +
                        '; '.join(f'{k}: {c.description}' for k, c in CELLS.items()))
    p.add_argument('--scenario', default=None, choices=sorted(SCENARIOS),
                   help='robot errors (default geometric, or the cell\'s)')
    p.add_argument('--error-model', default=ERROR_MODELS[0], choices=ERROR_MODELS,
                   help='geometric errors: 6-DoF on every joint origin, or the prototype\'s DH '
                        'errors (offset, a, d, alpha; for DH-built URDFs)')
    p.add_argument('--seed', type=number_arg(int, 0, 2 ** 32 - 1), default=0)
    p.add_argument('--duration', type=number_arg(float, maximum=86400.0), default=60.0,
                   help='seconds of teleoperation (> 2, at most a day)')
    p.add_argument('--storage', default='mcap', choices=['mcap', 'sqlite3'])
    p.add_argument('--compressed', default=None, choices=['none', 'png', 'jpeg'],
                   help='publish sensor_msgs/CompressedImage on /<cam>/image_raw/compressed '
                        '(default: the cell\'s transport)')
    p.add_argument('--encoding', default=None, choices=['mono8', 'rgb8', 'bgr8'],
                   help='image encoding (default: the cell\'s)')
    p.add_argument('--no-zstd', action='store_true', help='no zstd chunk compression (mcap)')
    p.add_argument('--knock', action='append', default=[], metavar='CAM:TIME:DEG:MM',
                   help='knock camera CAM TIME s into the session: it turns by DEG degrees '
                        'about a random axis through its optical centre and the centre moves '
                        'by MM mm (repeatable)')
    p.add_argument('--refocus', action='append', default=[], metavar='CAM:TIME:PERCENT',
                   help='change camera CAM\'s focal length (fx, fy) by PERCENT %% TIME s into '
                        'the session (repeatable)')
    from armcal_ros.sim.cells import AMBIENT, LAMP_HEIGHT_M, LIGHTINGS
    p.add_argument('--lighting', default='realistic', choices=LIGHTINGS,
                   help=f'realistic (default): the marker, a matte ball, lit by one lamp '
                        f'{LAMP_HEIGHT_M:g} m above the workspace\'s centre, its far side '
                        f'keeping {AMBIENT:g} of the full brightness; uniform: a ball that '
                        f'glows alike from every side (--lamp and --led replace either)')
    p.add_argument('--lamp', type=number_arg(float, -1000.0, 1000.0), nargs=3, default=None,
                   metavar=('X', 'Y', 'Z'),
                   help='light the marker, a matte ball, by one lamp at X Y Z (m, base frame) '
                        'instead of the realistic lamp')
    p.add_argument('--led', type=number_arg(float, -1000.0, 1000.0), nargs=3, default=None,
                   metavar=('AX', 'AY', 'AZ'),
                   help='make the marker an LED in a diffusing ball pointing along AX AY AZ '
                        '(the marker link\'s frame): brightest where it points, so the bright '
                        'side turns with the tool (not with --lamp)')
    p.add_argument('--led-falloff', type=number_arg(float, 0.1, 100.0), default=1.0,
                   help='with --led: the exponent m of its beam, cos^m of the angle off its '
                        'axis (1: a Lambertian LED; larger: narrower; default 1)')
    p.add_argument('--ambient', type=number_arg(float, 0.0, 1.0), default=0.25,
                   help='a lit marker (realistic, --lamp or --led): the fraction of the full '
                        'brightness the ball\'s unlit side keeps (default 0.25)')
    p.add_argument('--stamp-latency', action='append', default=[], metavar='CAM:SECONDS',
                   help='camera CAM\'s driver stamps each image SECONDS after its exposure '
                        '(repeatable; the ground truth keeps the exposure times)')
    p.add_argument('--joint-jitter', type=number_arg(float, 0.0, 1.0), default=0.0,
                   metavar='S', help='std (s) of the joint states\' stamps about the control '
                                     'clock')
    p.add_argument('--joint-drop', type=number_arg(float, 0.0, 0.99), default=0.0,
                   metavar='F', help='fraction of the joint states lost')
    p.add_argument('--backlash', type=number_arg(float, 0.0, 10.0), default=0.0, metavar='DEG',
                   help='play of every joint (deg): the links lag the readings by half of it '
                        'against the last motion')
    p.add_argument('--repeatability', type=number_arg(float, 0.0, 100.0), default=0.0,
                   metavar='MM', help='std per axis (mm) of where each stop really ends')
    p.add_argument('--settle', type=number_arg(float, 0.0, 100.0), nargs=3, default=None,
                   metavar=('MM', 'HZ', 'TAU'),
                   help='after each stop the structure rings down: MM mm at HZ Hz, decaying '
                        'with time constant TAU s (e.g. 0.1 10 0.1)')
    p.add_argument('--read-noise', type=number_arg(float, 0.0, 20.0), default=None,
                   metavar='DN', help='the sensor\'s read noise (DN, 8-bit; default the '
                                      'cell\'s 0.06)')
    p.add_argument('--clutter', type=number_arg(float, 0.0, 200.0), default=None, metavar='DN',
                   help='a textured static scene behind the marker, mean brightness DN '
                        '(default the cell\'s; 0: black)')
    p.add_argument('--exposure-steps', type=number_arg(float, 0.01, 1000.0), nargs=2,
                   default=None, metavar=('PERIOD', 'F'),
                   help='auto-exposure: every PERIOD s each camera\'s brightness is set anew, '
                        'a factor in [1/F, F]')
    p.add_argument('--lens-k3', type=number_arg(float, -0.99, 0.99), default=0.0, metavar='K3',
                   help='every camera\'s k3 (x 0.8-1.2 per camera; default 0)')
    p.add_argument('--lens-tangential', type=number_arg(float, 0.0, 0.0199), default=0.0,
                   metavar='P', help='std of every camera\'s p1, p2 (default 0: 5e-4)')
    p.add_argument('--rolling-shutter', type=number_arg(float, 0.0, 0.199), default=0.0,
                   metavar='S', help='readout time (s) of a rolling shutter, first row to last '
                                     '(default 0: global shutter)')
    p.add_argument('--pause', type=number_arg(float, 0.05, 60.0), nargs=2, default=None,
                   metavar=('MIN', 'MAX'),
                   help='the operator\'s stops last MIN to MAX s (default the cell\'s '
                        '0.4 1.2)')
    p.add_argument('--joint-rate', type=number_arg(float, 1.0, 10000.0), default=None,
                   metavar='HZ', help='joint states per second (default the cell\'s 200)')
    p.add_argument('--frame-id-format', default='{camera}_optical_frame',
                   help='the images\' header.frame_id, {camera} standing for the camera\'s name '
                        '(e.g. {camera}_color_optical_frame as a RealSense driver names it)')
    p.add_argument('--quiet', action='store_true')


#: option -> (expected form, example, CameraChange fields after the camera and the time)
_CHANGE_OPTIONS = {
    '--knock': ('CAM:TIME:DEG:MM', 'cam1:30:0.5:2', ('rotation_deg', 'translation_mm')),
    '--refocus': ('CAM:TIME:PERCENT', 'cam1:30:1.5', ('focal_percent',)),
}


def _camera_change(option, text, camera_names, duration):
    """Return the CameraChange of one ``--knock`` or ``--refocus`` value."""
    from armcal_ros.sim.cell import CameraChange
    form, example, names = _CHANGE_OPTIONS[option]
    parts = text.rsplit(':', len(names) + 1)
    try:
        if len(parts) != len(names) + 2:
            raise ValueError(f'{len(parts)} fields')
        values = [float(v) for v in parts[1:]]
        if not all(math.isfinite(v) for v in values):
            raise ValueError('every number must be finite')
        change = CameraChange(parts[0], values[0], **dict(zip(names, values[1:])))
    except ValueError as err:
        raise ValueError(f'{option} expects {form} (e.g. {example}), got {text!r}: {err}') \
            from None
    if change.camera not in camera_names:
        raise ValueError(f'{option} {text!r}: unknown camera {change.camera!r}; the cell\'s '
                         f'cameras are {list(camera_names)}')
    if change.time_s >= duration:
        raise ValueError(f'{option} {text!r}: TIME must be before the end of the session '
                         f'(--duration {duration:g})')
    return change


def _run_simulate(args):
    import dataclasses
    import os

    import yaml

    from armcal_ros.sim.cell import simulate_cell
    from armcal_ros.sim.cells import cell_parameters, get_cell
    from armcal_ros.sim.output import write_sim_bag
    from armcal_ros.sim.true_geometry import write_true_geometry
    if os.path.exists(args.output):
        raise ValueError(f'--output {args.output} exists already; choose a new bag directory')
    if args.duration <= 2.0:
        raise ValueError(f'--duration must be > 2 s, got {args.duration}')
    try:
        args.frame_id_format.format(camera='cam')
        ok = '{camera}' in args.frame_id_format
    except (KeyError, IndexError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f'--frame-id-format must contain {{camera}} and no other field, got '
                         f'{args.frame_id_format!r}')
    cell = get_cell(args.cell)
    scenario = args.scenario or cell.scenario
    compressed = cell.compressed if args.compressed is None else \
        (None if args.compressed == 'none' else args.compressed)
    encoding = args.encoding or cell.encoding
    own_light = args.lamp is not None or args.led is not None
    settings = cell.sim_settings('uniform' if own_light else args.lighting,
                                 error_model=args.error_model)
    changes = tuple(_camera_change(option, text, settings.camera_names, args.duration)
                    for option, texts in (('--knock', args.knock), ('--refocus', args.refocus))
                    for text in texts)
    if changes:
        settings = dataclasses.replace(settings, camera_changes=changes)
    if args.lamp is not None and args.led is not None:
        raise ValueError('--lamp and --led are two kinds of marker: give one')
    if settings.sensor.lamp is not None:
        settings = dataclasses.replace(settings, sensor=dataclasses.replace(
            settings.sensor, ambient=args.ambient))
    if args.lamp is not None:
        settings = dataclasses.replace(settings, sensor=dataclasses.replace(
            settings.sensor, lamp=tuple(args.lamp), ambient=args.ambient))
    if args.led is not None:
        try:
            settings = dataclasses.replace(settings, sensor=dataclasses.replace(
                settings.sensor, led_axis=tuple(args.led), led_falloff=args.led_falloff,
                ambient=args.ambient))
        except ValueError as exc:
            raise ValueError(f'--led: {exc}') from exc
    latency = [0.0] * len(settings.camera_names)
    for text in args.stamp_latency:
        cam, _, value = text.rpartition(':')
        try:
            seconds = float(value)
            if not (math.isfinite(seconds) and abs(seconds) <= 1.0):
                raise ValueError('SECONDS must be finite and within 1 s')
        except ValueError as err:
            raise ValueError(f'--stamp-latency expects CAM:SECONDS (e.g. cam1:0.03), got '
                             f'{text!r}: {err}') from None
        if cam not in settings.camera_names:
            raise ValueError(f'--stamp-latency {text!r}: unknown camera {cam!r}; the cell\'s '
                             f'cameras are {list(settings.camera_names)}')
        latency[list(settings.camera_names).index(cam)] = seconds
    settle = args.settle or (0.0, 10.0, 0.1)
    if args.settle is not None and not (settle[1] > 0 and settle[2] > 0):
        raise ValueError(f'--settle HZ and TAU must be > 0, got {settle[1]} and {settle[2]}')
    settings = dataclasses.replace(
        settings, stamp_latency=tuple(latency) if args.stamp_latency else (),
        joint_jitter=args.joint_jitter, joint_drop=args.joint_drop,
        backlash_deg=args.backlash, repeatability_mm=args.repeatability,
        settle_mm=settle[0], settle_hz=settle[1], settle_tau=settle[2],
        rolling_shutter=args.rolling_shutter, lens_k3=args.lens_k3,
        lens_tangential=args.lens_tangential,
        dwell=tuple(args.pause) if args.pause else settings.dwell,
        joint_rate=args.joint_rate or settings.joint_rate)
    sensor = {}
    if args.read_noise is not None:
        sensor['read_noise'] = args.read_noise
    if args.clutter is not None:
        sensor['clutter_level'] = args.clutter
    if args.exposure_steps is not None:
        sensor['exposure_steps'] = tuple(args.exposure_steps)
    if sensor:
        settings = dataclasses.replace(settings, sensor=dataclasses.replace(settings.sensor,
                                                                            **sensor))
    result = simulate_cell(scenario, args.seed, args.duration, settings)

    live = not args.quiet and sys.stderr.isatty()   # '\r' updates only on a terminal

    def progress(i, n):
        if live:
            print(f'\r  writing {i}/{n} messages', end='', file=sys.stderr, flush=True)

    counts = write_sim_bag(result, args.output, storage=args.storage,
                           compressed=compressed, encoding=encoding,
                           compress=not args.no_zstd, progress=progress,
                           frame_id_format=args.frame_id_format)
    params = os.path.join(args.output, 'ground_truth', 'params.yaml')
    with open(params, 'w', encoding='utf-8') as f:
        f.write(f'# calibrator parameters for this simulated cell ({args.cell}):\n'
                f'#   armcal calibrate {args.output} --params {params}\n')
        values = cell_parameters(settings, compressed)
        yaml.safe_dump({'armcal': {'ros__parameters': values}}, f, sort_keys=False)
    write_true_geometry(result, os.path.dirname(params), values)
    if live:
        print('', file=sys.stderr)
    if not args.quiet:
        size = sum(os.path.getsize(os.path.join(d, f))
                   for d, _, fs in os.walk(args.output) for f in fs)
        print(f'wrote {args.output}: cell {args.cell}, scenario {scenario}, seed {args.seed}, '
              f'{len(result.dwells)} dwells, '
              + ', '.join(f'{t} {n}' for t, n in counts.items())
              + (f'; {len(changes)} camera changes (ground_truth/changes.yaml)'
                 if changes else '')
              + f'; {size / 1e6:.1f} MB; calibrator parameters in {params}')
    return 0


# ---- import-folder ----------------------------------------------------------------------

def _add_import_folder(p):
    p.add_argument('folder', metavar='DIR', help='a folder of captures: poses.csv (or '
                   'ee_poses.csv) and images/<prefix><sample>_<camera>.jpg|png (README)')
    p.add_argument('--output', required=True, metavar='BAG', help='bag directory to create')
    p.add_argument('--pose-topic', default='/tool_pose', help='topic of the link poses')
    p.add_argument('--base-frame', default='base_link')
    p.add_argument('--marker-link', default='tool0', help='the link whose pose the table gives')
    p.add_argument('--storage', default='mcap', choices=['mcap', 'sqlite3'])


def _run_import_folder(args):
    import os

    from armcal_ros.io.folder_import import read_capture_folder, write_capture_bag
    if os.path.exists(args.output):
        raise ValueError(f'--output {args.output} exists already; choose a new bag directory')
    folder = read_capture_folder(args.folder)
    params = write_capture_bag(folder, args.output, args.pose_topic, args.base_frame,
                               args.marker_link, args.storage)
    arm = 'link poses' if folder.poses is not None else 'joint angles'
    given = sorted(folder.intrinsics) or 'none'
    print(f'wrote {args.output}: {len(folder.samples)} captures ({arm}), cameras '
          f'{folder.cameras}, intrinsics given for {given}; parameters in {params}')
    return 0


#: name -> (help, add_arguments(parser), run(args) -> exit status).
#: Other subcommands (calibrate, replay, report, demo) register here the same way.
SUBCOMMANDS = {
    'simulate': ('simulate a calibration cell into a rosbag2 bag with ground truth',
                 _add_simulate, _run_simulate),
    'import-folder': ('turn a folder of images and poses (or joint angles) per capture into a '
                      'rosbag2 bag with CameraInfo and a parameter file',
                      _add_import_folder, _run_import_folder),
    'replay': ('publish a bag\'s messages with their timing (like ros2 bag play) to drive the '
               'node', _add_replay, _run_replay),
    'calibrate': ('calibrate the cameras from a recorded rosbag2 bag (no ROS middleware needed)',
                  lambda p: _offline().add_arguments(p), lambda a: _offline().run(a)),
    'demo': ('calibrate the bundled demo bag and compare with its ground truth',
             lambda p: _demo().add_arguments(p), lambda a: _demo().run(a)),
}


def _demo():
    from armcal_ros import demo
    return demo


def _offline():
    from armcal_ros import offline
    return offline


def build_parser():
    """Return the argparse parser with every registered subcommand."""
    parser = argparse.ArgumentParser(prog='armcal', description='Online camera calibration '
                                     'with a robot arm as the target.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for name, (help_text, add, _) in SUBCOMMANDS.items():
        add(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def main(argv=None):
    """Entry point of the ``armcal`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _, _, run = SUBCOMMANDS[args.command]
    try:
        return int(run(args) or 0)
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        print(f'armcal {args.command}: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # One line and the shell's status for SIGINT; an output directory is only ever
        # replaced as a whole at the end (io/output_dir.py), so it is as it was.
        print(f'\narmcal {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
