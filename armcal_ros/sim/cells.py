"""
Named cells for the simulator: arms, camera sets and image transports beyond the demo's.

The calibrator must work in cells it has never seen, so the benchmarks and tests run it on
several that differ from the demo in everything a user's cell can differ in (bench/cells.py):

- ``puma-3cam``: the demo's cell (PUMA 560 by DH, cam1..cam3, raw mono8 images);
- ``ur5-2cam``: a UR5 laid out as ur_description does it (rotated base, rpy joint origins,
  fixed flange/tool0), two cameras ``left`` and ``right``, CompressedImage JPEG in colour;
- ``desk-4cam``: a small desktop arm laid out in URDF style rather than by DH (pitch joints about
  y, a continuous roll joint), a half-size workspace seen by four cameras at about 1 m
  (``overhead``, ``front``, ``side_a``, ``side_b``), CompressedImage PNG mono;
- ``puma-3cam-clutter``: the demo's arm and cameras, but exposed for the scene: a cluttered
  static background and six static round spots per camera as bright as the marker;
- ``puma-1cam-glints``: one camera (``wrist_view``), raw bgr8, forty times the default rate of
  spurious highlights, half of them near the marker.

Every cell publishes its joints in a random order with an extra gripper joint (as
:func:`~armcal_ros.sim.cell.simulate_cell` always does), and its marker - a matte ball - is lit
as in a real cell (``lighting='realistic'``, the default): by one lamp
:data:`LAMP_HEIGHT_M` above the workspace's centre, its far side keeping :data:`AMBIENT` of the
full brightness from the room.  Each camera then sees the lit side at another angle and the
ball's intensity centroid moves towards it by about half a pixel (docs/BENCHMARKS.md,
*realism*).  ``lighting='uniform'`` is the ideal ball that glows alike from every side.

A cell names only geometry, light and transport; the calibrator's own parameters for it come
from :func:`cell_parameters` (the camera names, topics and URDF a user would write into their
parameter file - nothing tuned).
"""

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from armcal_ros.sim.cell import bundled_urdf, default_urdf_path, SimSettings
from armcal_ros.sim.output import image_topic


@dataclass(frozen=True)
class Cell:
    """
    A simulated cell: settings overrides, the default scenario and the image transport.

    ``urdf`` is the file name of a URDF bundled with the package (``urdf/``).
    """

    description: str
    urdf: str
    settings: dict = field(default_factory=dict)
    scenario: str = 'geometric'
    compressed: Optional[str] = None     # None (sensor_msgs/Image), 'png' or 'jpeg'
    encoding: str = 'mono8'

    def sim_settings(self, lighting='realistic', **overrides) -> SimSettings:
        """
        Return the SimSettings of this cell (``overrides`` replace fields).

        ``lighting`` one of :data:`LIGHTINGS` (:func:`with_lighting`).
        """
        return with_lighting(SimSettings(**{'urdf_path': bundled_urdf(self.urdf),
                                            **self.settings, **overrides}), lighting)


#: How a cell's marker is lit: ``realistic`` (a matte ball under one lamp above the cell) or
#: ``uniform`` (a ball that glows alike from every side: its centroid is its centre).
LIGHTINGS = ('realistic', 'uniform')
#: The realistic lamp's height above the workspace's centre (m): a ceiling or gantry light
#: over a cell whose cameras stand 1-2 m from the arm.
LAMP_HEIGHT_M = 1.5
#: The fraction of the full brightness a ball's unlit side keeps from the room's other light
#: (walls, windows): a quarter is an ordinary indoor contrast between lit and shaded sides.
AMBIENT = 0.25


def realistic_lamp(settings: SimSettings) -> tuple:
    """Return the realistic lamp's base-frame position: :data:`LAMP_HEIGHT_M` above the centre."""
    centre = 0.5 * (np.asarray(settings.workspace_min, float) +
                    np.asarray(settings.workspace_max, float))
    return tuple(float(v) for v in centre + np.array([0.0, 0.0, LAMP_HEIGHT_M]))


def with_lighting(settings: SimSettings, lighting: str) -> SimSettings:
    """
    Return ``settings`` with its marker lit as ``lighting`` says (one of :data:`LIGHTINGS`).

    ``realistic`` hangs :func:`realistic_lamp` with :data:`AMBIENT` unless the settings light
    the marker already (a lamp or an LED of their own); ``uniform`` takes any light away.
    """
    if lighting not in LIGHTINGS:
        raise ValueError(f'lighting must be one of {list(LIGHTINGS)}, got {lighting!r}')
    sensor = settings.sensor
    if lighting == 'uniform':
        sensor = dataclasses.replace(sensor, lamp=None, led_axis=None)
    elif sensor.lamp is None and sensor.led_axis is None:
        sensor = dataclasses.replace(sensor, lamp=realistic_lamp(settings), ambient=AMBIENT)
    return dataclasses.replace(settings, sensor=sensor)


CELLS = {
    'puma-3cam': Cell('PUMA 560 (DH), cam1..cam3, raw mono8 (the demo cell)',
                      'puma560.urdf'),
    'ur5-2cam': Cell('UR5 (ur_description layout), left/right, CompressedImage JPEG rgb8',
                     'ur5.urdf', dict(joint_range_deg=None, camera_names=('left', 'right')),
                     compressed='jpeg', encoding='rgb8'),
    'desk-4cam': Cell('desktop arm (URDF-style axes, 0.5 m reach), 4 cameras at ~1 m, '
                      'CompressedImage PNG mono8',
                      'desk_arm6.urdf',
                      dict(joint_range_deg=None, workspace_min=(0.12, -0.25, 0.05),
                           workspace_max=(0.42, 0.25, 0.45), camera_distance=(0.8, 1.2),
                           camera_height=(0.3, 0.7), link_radius=0.025,
                           camera_names=('overhead', 'front', 'side_a', 'side_b')),
                      scenario='mixed', compressed='png'),
    'puma-3cam-clutter': Cell('PUMA 560, cam1..cam3 exposed for the scene: a cluttered '
                              'background and 6 static marker look-alikes per camera',
                              'puma560.urdf',
                              dict(sensor=dict(clutter_level=60.0, clutter_spots=6))),
    'puma-1cam-glints': Cell('PUMA 560, one camera, raw bgr8, 2 spurious highlights per frame',
                             'puma560.urdf',
                             dict(camera_names=('wrist_view',),
                                  sensor=dict(glint_rate=2.0, glint_near_marker=0.5)),
                             scenario='nongeometric', encoding='bgr8'),
}


def get_cell(name) -> Cell:
    """Return the cell ``name`` of :data:`CELLS` (ValueError naming the choices otherwise)."""
    if name not in CELLS:
        raise ValueError(f'cell must be one of {sorted(CELLS)}, got {name!r}')
    return CELLS[name]


def cell_parameters(settings: SimSettings, compressed=None, noise_model='auto') -> dict:
    """
    Return the calibrator parameters (``ros__parameters``) matching a simulated cell.

    Only what describes the cell: URDF, marker link, joint-state and image topics, camera
    names, and for an LED (whose bright side turns with the tool) the per-view shaded-ball
    centre; everything else keeps the node's defaults - a lamp's place too, which a user
    seldom knows and the default centre (``shaded_pooled``) does not need.
    """
    urdf = settings.urdf_path or default_urdf_path()
    names = list(settings.camera_names)
    out = dict(robot_description_file=urdf, base_frame=settings.base_frame,
               marker_link=settings.marker_link, marker_offset=list(settings.marker_offset),
               marker_type='sphere', joint_states_topic='/joint_states',
               camera_names=names, image_topics=[image_topic(n, compressed) for n in names],
               noise_model=noise_model)
    if settings.sensor.led_axis is not None:
        # An LED's bright side turns with the tool: no lamp to give, the per-view fit's centre.
        out.update(sphere_centre='shaded')
    return out


__all__ = ['AMBIENT', 'Cell', 'CELLS', 'cell_parameters', 'get_cell', 'LAMP_HEIGHT_M', 'LIGHTINGS',
           'realistic_lamp', 'with_lighting']
