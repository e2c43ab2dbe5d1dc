"""Objects from mesh files (inhand_sim.mesh_objects, .catalogue): the shipped meshes, distances
and their signs, contacts on the triangles, area-uniform samples, a user's mesh file through
simulate_session, and what is refused."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from inhand_common.ground_truth import load_truth, truth_path
from inhand_sim.catalogue import MESH_NAMES, load_object, mesh_folder
from inhand_sim.exploration import ExplorationSettings
from inhand_sim.mesh_objects import MeshError, MeshObject
from inhand_sim.session import SessionSettings, simulate
from inhand_sim.stereo_rig import StereoRig, compiled_sdf, render_pair, static_object_pose
from inhand_sim.triangles import closest_points_on_triangles
from ros_helpers import WORKSPACE, executable_path

FAST = ExplorationSettings(pool_size=150)
CM = 0.01


@pytest.fixture(scope='module')
def cup() -> MeshObject:
    obj = load_object('cup')
    assert isinstance(obj, MeshObject)
    return obj


@pytest.fixture(scope='module')
def cup_session():
    return simulate(SessionSettings(object_name='cup', static=True, rate=240.0, duration=8.0,
                                    seed=3, exploration=FAST))


def brute_force_distance(obj: MeshObject, points: np.ndarray) -> np.ndarray:
    """Distance from each point to every triangle, the least (no bins, no grid)."""
    t = obj.triangles
    out = np.empty(len(points))
    for i, p in enumerate(points):
        q = closest_points_on_triangles(np.broadcast_to(p, (len(t), 3)), t[:, 0], t[:, 1], t[:, 2])
        out[i] = np.linalg.norm(q - p, axis=1).min()
    return out


def box_stl(path, size_mm=(100.0, 40.0, 20.0), drop_face: bool = False) -> None:
    """A box (mm) as binary STL: 12 triangles of very different sizes."""
    mesh = trimesh.creation.box(extents=size_mm)
    if drop_face:
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)
    path.write_bytes(mesh.export(file_type='stl'))


# --- the shipped meshes ---------------------------------------------------------------------

def test_shipped_meshes_are_small_closed_and_sized_like_hand_held_objects():
    for name in MESH_NAMES:
        path = mesh_folder() / f'{name}.ply'
        assert path.stat().st_size < 600_000, name
        mesh = trimesh.load(path)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0, name
        assert 0.05 <= mesh.extents.max() <= 0.16, name
    assert trimesh.load(mesh_folder() / 'cup.ply').euler_number == 0      # the handle's hole


def test_make_meshes_regenerates_the_shipped_meshes_bit_for_bit(tmp_path):
    result = subprocess.run([sys.executable, str(WORKSPACE / 'launch_scripts' / 'make_meshes.py'),
                             str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    for name in MESH_NAMES:
        made = hashlib.sha256((tmp_path / f'{name}.ply').read_bytes()).hexdigest()
        shipped = hashlib.sha256((mesh_folder() / f'{name}.ply').read_bytes()).hexdigest()
        assert made == shipped, name


def test_the_cup_is_solid_in_its_wall_handle_and_bottom_and_empty_in_its_cavity(cup):
    # cup.ply (launch_scripts/make_meshes.py): axis 4.1 cm (the rim's radius) in from the far
    # side, 9.5 cm tall, wall 5 mm (outer radius 3.7 cm at the foot, 4.1 cm at the rim),
    # bottom 7 mm, handle a tube of 5.5 mm round a circle of 2.55 cm centred 4.75 cm out
    axis = cup.bounds[0, 0] + 4.1 * CM
    foot = cup.table_z

    def at(x, z):      # x from the axis towards the handle, z above the foot
        return np.array([axis + x, 0.0, foot + z])
    cavity = np.array([at(0.0, 5 * CM), at(2.5 * CM, 8 * CM), at(-2.5 * CM, 2 * CM)])
    wall = np.array([at(3.65 * CM, 5 * CM), at(-3.7 * CM, 8 * CM), at(0.0, 0.35 * CM)])
    handle = np.array([at(7.3 * CM, 4.9 * CM)])
    loop = np.array([at(4.75 * CM, 4.9 * CM)])            # the hole the handle goes round
    assert np.all(cup.sdf(cavity) > 0.007) and cup.sdf(cavity[:1])[0] > 3 * CM
    assert np.all(cup.sdf(wall) < -0.001) and cup.sdf(handle)[0] < -0.003
    assert cup.sdf(loop)[0] > 0.005
    # near the surface the grid's distances are the triangles' (signed by the cavity side)
    rng = np.random.default_rng(1)
    samples, normals = cup.sample_surface(300, rng)
    offset = rng.uniform(-0.002, 0.002, 300)
    points = samples + offset[:, None] * normals
    exact = brute_force_distance(cup, points)
    signed = cup.sdf(points)
    clear = np.abs(offset) > 0.0005
    assert np.all(np.sign(signed[clear]) == np.sign(offset[clear]))
    assert np.max(np.abs(np.abs(signed) - exact)) < 0.0005
    assert np.median(np.abs(np.abs(signed) - exact)) < 2e-5
    # the renderer's compiled kernel interpolates the same numbers
    far = rng.uniform(cup.bounds[0] - 0.05, cup.bounds[1] + 0.05, (2000, 3))
    assert np.array_equal(compiled_sdf(cup, far), cup.sdf(far))


def test_projection_puts_points_on_the_triangles(cup):
    rng = np.random.default_rng(2)
    samples, normals = cup.sample_surface(400, rng)
    points = samples + rng.uniform(-0.004, 0.008, (400, 1)) * normals
    projected = cup.project_to_surface(points)
    assert brute_force_distance(cup, projected[:50]).max() < 1e-12
    _, distance, _ = cup.closest_points(projected)
    assert distance.max() < 1e-12
    assert np.median(np.linalg.norm(projected - samples, axis=1)) < 2e-4


def test_contacts_are_on_the_cup_inside_and_out_and_strays_above_it(cup_session):
    truth, cup = cup_session.truth, cup_session.object
    _, distance, _ = cup.closest_points(truth['contacts'])
    assert distance.max() < 5e-5          # on the triangles (the brief: within 0.05 mm)
    assert distance.max() < 1e-10         # in fact exactly
    # the fingers reach into the cavity (the fingertip fits there): contacts on the inner wall
    # (normals towards the axis) and on the floor inside
    axis = np.array([cup.bounds[0, 0] + 4.1 * CM, 0.0])
    towards = truth['contacts'][:, :2] - axis
    radial = np.linalg.norm(towards, axis=1)
    _, _, face = cup.closest_points(truth['contacts'])
    normal = cup.face_normals[face]
    wall = np.sum(normal[:, :2] * towards, axis=1) / radial < -0.5
    floor = (normal[:, 2] > 0.9) & (truth['contacts'][:, 2] < cup.table_z + 1.5 * CM)
    inside = (wall | floor) & (radial < 3.7 * CM)
    assert inside.mean() > 0.05
    # strays: off the triangles, the nearest ones a fraction of a millimetre up
    near = truth['stray_points'][cup.sdf(truth['stray_points']) < 0.003]
    height = brute_force_distance(cup, near[:: max(1, len(near) // 150)])
    assert height.min() >= 0.9 * FAST.min_height and np.any(height < 0.001)
    assert np.all(cup.sdf(truth['stray_points']) > 0.0)


def test_samples_are_uniform_by_area_and_grips_hold_their_share(tmp_path):
    box_stl(tmp_path / 'box.stl')
    box = load_object(str(tmp_path / 'box.stl'), scale=0.001)
    assert box.size == pytest.approx([0.1, 0.04, 0.02])
    points, normals = box.sample_surface(200_000, np.random.default_rng(3))
    area = 2 * (0.1 * 0.04 + 0.1 * 0.02 + 0.04 * 0.02)
    assert box.surface_area() == pytest.approx(area)
    top = np.abs(points[:, 2] - 0.01) < 1e-9
    assert top.mean() == pytest.approx(0.1 * 0.04 / area, rel=0.02)
    assert np.all(normals[top] == [0.0, 0.0, 1.0])
    # evenly over the top face, across its two triangles
    counts = np.histogram2d(points[top, 0], points[top, 1], bins=(10, 4))[0]
    assert counts.std() / counts.mean() < 0.06
    # every grip holds about its share of the surface
    assert box.static_grip.contains(points).mean() == pytest.approx(0.08, abs=0.01)
    for grip in box.moving_grips:
        assert 0.08 < grip.contains(points).mean() < 0.14


def test_a_mesh_file_round_trips_through_simulate_session(tmp_path):
    box_stl(tmp_path / 'block.stl')
    out = tmp_path / 'bags' / 'block'
    args = [executable_path('simulate_session'), '--object', str(tmp_path / 'block.stl'),
            '--mesh-scale', '0.001', '--static', '--rate', '15', '--duration', '4', '--seed', '2',
            '--output', str(out), '--quiet']
    result = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    truth = load_truth(truth_path(out))
    assert truth.object_name == str(tmp_path / 'block.stl')
    assert truth.settings['mesh_scale'] == 0.001
    assert len(truth.surface_points) >= 100_000
    half = np.array([0.05, 0.02, 0.01])
    assert np.all(np.abs(truth.surface_points) <= half + 1e-6)
    # every contact on a face of the box: one coordinate at its half extent
    on_face = np.isclose(np.abs(truth.contacts), half, atol=1e-9).any(axis=1)
    assert len(truth.contacts) > 50 and on_face.all()
    assert np.all(np.abs(truth.contacts) <= half + 1e-9)


def test_bad_meshes_are_refused_in_one_line(tmp_path):
    box_stl(tmp_path / 'open.stl', drop_face=True)
    (tmp_path / 'junk.ply').write_bytes(b'ply\nthis is not a mesh\n')
    box_stl(tmp_path / 'huge.stl', size_mm=(1000.0, 400.0, 200.0))
    box_stl(tmp_path / 'tiny.stl', size_mm=(10.0, 5.0, 5.0))
    cases = {'open.stl': 'not watertight', 'junk.ply': 'cannot read', 'huge.stl': 'cm across',
             'tiny.stl': 'cm across', 'missing.obj': 'no such mesh file'}
    for name, says in cases.items():
        with pytest.raises(MeshError, match=says):
            load_object(str(tmp_path / name), scale=0.001)
    with pytest.raises(ValueError, match='built-in'):
        load_object('cat', scale=0.001)
    # the command says it in one line and exits 2
    result = subprocess.run([executable_path('simulate_session'), '--object', str(tmp_path / 'open.stl'),
                             '--mesh-scale', '0.001', '--static', '--rate', '15', '--duration', '2',
                             '--seed', '1', '--output', str(tmp_path / 'x'), '--quiet'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.count('\n') == 1 and 'not watertight' in result.stderr
    assert not (tmp_path / 'x').exists()


def test_mesh_sessions_are_deterministic(cup_session):
    again = simulate(cup_session.settings)
    assert np.array_equal(again.poses, cup_session.poses)
    for key in ('contacts', 'stray_points', 'surface_points', 'surface_normals'):
        assert np.array_equal(again.truth[key], cup_session.truth[key])


def test_the_stereo_rig_renders_a_mesh_on_its_surface():
    duck = load_object('duck')
    rig = StereoRig(width=200, height=150, focal=600.0, cx=100.3, cy=74.6)
    shot = render_pair(rig, duck, static_object_pose(duck), np.random.default_rng(0), table=True)
    assert shot.mask.sum() > 3000
    on_object = shot.points('object')[shot.mask]
    _, distance, _ = duck.closest_points(on_object[:: max(1, len(on_object) // 400)])
    assert distance.max() < 5e-4
