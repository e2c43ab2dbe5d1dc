"""The stereo pictures of ``render_map`` (the paper's figs. 6 and 7).

Hand-made cases through ``draw_all`` (a sphere of cells, half of them textured in a colour
whose hue says whether RGB was drawn as RGB; a cloud of points on its camera side), then
``render_map`` on the bundled static cat with and without what the stereo pictures need:
the rig's config (camera_pose), the map's colours, a stereo pair in the bag.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from inhand_tools.commands.build_map import main as build_map_main
from inhand_tools.commands.render_map import main as render_map_main
from inhand_tools.map_cells import Lattice, MapCells, cell_indices
from inhand_tools.map_figures import StereoCloud, draw_all, near_cells
from pose_sessions import fibonacci_sphere, sphere_session, write_pose_bag
from ros_helpers import WORKSPACE

H = 0.005
RADIUS = 0.03
SIZE = 240
TEXTURE_RGB = (230, 120, 20)   # orange: OpenCV hue 14 (drawn as BGR by mistake: 105)
POINT_RGB = (40, 160, 230)     # sky blue: hue 101 (by mistake: 19)
STEREO_PICTURES = ('stereo_points.png', 'texture_registration.png')


def hue_of(rgb) -> float:
    pixel = np.array([[rgb[::-1]]], dtype=np.uint8)
    return float(cv2.cvtColor(pixel, cv2.COLOR_BGR2HSV)[0, 0, 0])


def sphere_points(count: int, radius: float = RADIUS) -> np.ndarray:
    return fibonacci_sphere(count, radius)


def sphere_cells(colours: bool = True, textured_side: bool = True) -> MapCells:
    """Occupied cells (p 0.9) on a sphere, a few unsure ones (p 0.3) inside; the cells
    facing +x (the camera) textured orange if ``textured_side``."""
    lattice = Lattice(H)
    surface = np.unique(cell_indices(sphere_points(20000), lattice), axis=0)
    inner = np.unique(cell_indices(sphere_points(2000, 0.5 * RADIUS), lattice), axis=0)
    centres = (np.concatenate([surface, inner]) + 0.5) * H
    probabilities = np.r_[np.full(len(surface), 0.9), np.full(len(inner), 0.3)]
    n = len(centres)
    cells = MapCells(centres, probabilities, np.zeros(n, np.int64), np.full(n, np.nan),
                     lattice, 'npz', 'hand-made sphere', True)
    if colours:
        textured = (centres[:, 0] > 0.01) & (probabilities > 0.8) & textured_side
        rgb = np.zeros((n, 3), np.uint8)
        rgb[textured] = TEXTURE_RGB
        cells.colours, cells.textured = rgb, textured
    return cells


def sphere_stereo(shift=(0.0, 0.0, 0.0)) -> StereoCloud:
    """Points of the sphere's camera side (+x), sky blue, and a sky-blue image."""
    points = sphere_points(30000)
    points = points[points[:, 0] > 0.005] + np.asarray(shift)
    image = np.empty((90, 120, 3), np.uint8)
    image[:] = POINT_RGB
    return StereoCloud(points, np.tile(np.array(POINT_RGB, np.uint8), (len(points), 1)),
                       image, 1, np.array([0.4, 0.0, 0.05]))


def panel_pixels(path, panel: int, size: int = SIZE) -> np.ndarray:
    """The pixels (k, 3) BGR of one square panel's drawing area: not its title, subtitles,
    scale bar or axes."""
    image = cv2.imread(str(path))
    assert image is not None, path
    square = image[40:40 + size, panel * size:(panel + 1) * size]
    keep = np.ones(square.shape[:2], bool)
    keep[:64] = False                       # title, subtitles, frame label
    keep[size - 30:] = False                # scale bar
    keep[size - 95:, size - 95:] = False    # the data frame's axes
    return square[keep]


def saturated_hues(pixels: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(pixels.reshape(-1, 1, 3), cv2.COLOR_BGR2HSV).reshape(-1, 3)
    return hsv[(hsv[:, 1] > 100) & (hsv[:, 2] > 60), 0].astype(float)


def near_hue(hues: np.ndarray, rgb, tolerance: float = 8.0) -> float:
    """Fraction of ``hues`` within ``tolerance`` of ``rgb``'s (OpenCV hue, 0-180)."""
    difference = np.abs(hues - hue_of(rgb))
    return float(np.mean(np.minimum(difference, 180 - difference) <= tolerance))


@pytest.fixture(scope='module')
def drawn(tmp_path_factory):
    out = tmp_path_factory.mktemp('stereo_pictures')
    written = draw_all(sphere_cells(), out, [0.0, 0.6, 0.8], None, None, 'object',
                       size=SIZE, stereo=sphere_stereo())
    return out, written


def test_the_stereo_pictures_are_written_and_in_the_overview(drawn):
    out, written = drawn
    names = [path.name for path in written]
    for name in ('stereo_points.png', 'textured_map.png', 'texture_registration.png',
                 'figure.png'):
        assert name in names and (out / name).stat().st_size > 0, name
    stereo = cv2.imread(str(out / 'stereo_points.png'))
    # Oblique and side views, then the image at the panel height (120 x 90: 4:3).
    assert stereo.shape[0] == 40 + SIZE and stereo.shape[1] > 2 * SIZE + SIZE // 2
    textured = cv2.imread(str(out / 'textured_map.png'))
    assert textured.shape[1] == 3 * SIZE  # oblique, side, from the stereo camera
    # figure.png: 3 thresholds, regions, stereo points, textured map: 6 panels in rows of 3.
    figure = cv2.imread(str(out / 'figure.png'))
    assert figure.shape[1] == 3 * SIZE and figure.shape[0] > 2 * SIZE
    assert near_hue(saturated_hues(figure.reshape(-1, 3)), TEXTURE_RGB) > 0.05
    assert near_hue(saturated_hues(figure.reshape(-1, 3)), POINT_RGB) > 0.05


def test_textured_cells_are_drawn_in_their_camera_colours(drawn):
    out, _ = drawn
    for panel in range(3):
        pixels = panel_pixels(out / 'textured_map.png', panel)
        hues = saturated_hues(pixels)
        # The map's colours are RGB: drawn as such (orange, not the blue of BGR mix-ups).
        assert len(hues) > 150, panel
        assert near_hue(hues, TEXTURE_RGB) > 0.95, (panel, np.median(hues))
        # The cells the camera did not see are neutral grey.
        hsv = cv2.cvtColor(pixels.reshape(-1, 1, 3), cv2.COLOR_BGR2HSV).reshape(-1, 3)
        assert np.count_nonzero((hsv[:, 1] < 20) & (hsv[:, 2] > 80) & (hsv[:, 2] < 200)) > 150
    # Seen from the camera, the textured side fills most of the sphere's picture.
    camera_view = saturated_hues(panel_pixels(out / 'textured_map.png', 2))
    side_view = saturated_hues(panel_pixels(out / 'textured_map.png', 1))
    assert len(camera_view) > len(side_view)


def test_stereo_points_and_image_in_their_own_colours(drawn):
    out, _ = drawn
    for panel in range(2):
        hues = saturated_hues(panel_pixels(out / 'stereo_points.png', panel))
        assert len(hues) > 150 and near_hue(hues, POINT_RGB) > 0.95, panel
    image = cv2.imread(str(out / 'stereo_points.png'))[40 + 70:40 + SIZE - 10, 2 * SIZE + 10:-10]
    assert near_hue(saturated_hues(image), POINT_RGB) > 0.95
    registration = saturated_hues(panel_pixels(out / 'texture_registration.png', 2))
    assert len(registration) > 150 and near_hue(registration, POINT_RGB) > 0.95


def test_registration_counts_the_points_near_the_map(tmp_path, panel_labels):
    labels = panel_labels
    cells = sphere_cells()
    draw_all(cells, tmp_path, [0.8], None, None, 'object', size=160, stereo=sphere_stereo())
    registered = {subtitle.split('\n')[0] for _, subtitle in labels if 'within a cell' in subtitle}
    assert len(registered) == 1 and registered.pop().startswith('100% of the'), labels
    assert any(title == 'from the stereo camera' for title, _ in labels)
    # 3 cm off: the points miss the map.
    occupied = cells.centres[cells.probabilities > 0.8]
    stereo = sphere_stereo((0.03, 0.0, 0.0))
    assert near_cells(stereo.points, occupied, H).mean() < 0.2
    assert near_cells(sphere_stereo().points, occupied, H).all()


def test_without_colours_or_stereo_no_stereo_pictures(tmp_path):
    plain = tmp_path / 'plain'
    written = draw_all(sphere_cells(colours=False), plain, [0.0, 0.8], None, None, 'object',
                       size=160)
    names = {path.name for path in written}
    assert 'figure.png' in names and 'map_above_0.8.png' in names
    assert not names & {'textured_map.png', *STEREO_PICTURES}
    # A map with colours none of whose cells the camera saw: all grey, nothing coloured.
    grey = tmp_path / 'grey'
    written = draw_all(sphere_cells(textured_side=False), grey, [0.8], None, None, 'object',
                       size=SIZE)
    assert grey / 'textured_map.png' in written
    assert not {path.name for path in written} & set(STEREO_PICTURES)
    # No textured side to look from (no camera known): the oblique and side views only.
    assert cv2.imread(str(grey / 'textured_map.png')).shape[1] == 2 * SIZE
    for panel in range(2):
        assert len(saturated_hues(panel_pixels(grey / 'textured_map.png', panel))) < 10


# ------------------------------------------------------------------ render_map on a bag

CAT = WORKSPACE / 'bags' / 'cat_static'
STATIC = WORKSPACE / 'config' / 'mapping_static.yaml'
STEREO = WORKSPACE / 'config' / 'stereo.yaml'


@pytest.fixture(scope='module')
def cat_maps(tmp_path_factory):
    """The static cat's map with colours and without, and a sphere bag without images."""
    if not CAT.exists():
        pytest.skip(f'{CAT} is missing (bash launch_scripts/make_bags.sh)')
    root = tmp_path_factory.mktemp('cat_maps')
    for name, configs in (('coloured', [STATIC, STEREO]), ('plain', [STATIC])):
        args = [str(CAT), '--output-dir', str(root), '--name', name, '--quiet']
        for config in configs:
            args += ['--config', str(config)]
        assert build_map_main(args) == 0
    frames, _ = sphere_session(seconds=2.0, surface_points=30, moving=False, seed=3)
    sphere = write_pose_bag(root / 'sphere', frames)
    assert build_map_main([str(sphere), '--config', str(STATIC), '--output-dir', str(root),
                           '--name', 'sphere', '--quiet']) == 0
    return {'coloured': root / 'coloured.npz', 'plain': root / 'plain.npz',
            'sphere': root / 'sphere.npz', 'sphere_bag': sphere}


def run_render(capsys, *args):
    code = render_map_main([str(arg) for arg in args] + ['--size', '160'])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert 'Traceback' not in printed.err
    return [line for line in printed.out.split() if line.endswith('.png')], printed.err


def test_render_map_draws_the_stereo_pictures_of_the_bag(cat_maps, tmp_path, capsys):
    out = tmp_path / 'all'
    written, err = run_render(capsys, cat_maps['coloured'], '--bag', CAT, '--config', STATIC,
                              '--config', STEREO, '--output', out)
    assert 'note:' not in err, err
    for name in ('raw_points', 'registered_points', 'stereo_points', 'map_above_0.8',
                 'textured_map', 'texture_registration', 'regions', 'truth', 'figure'):
        assert str(out / f'{name}.png') in written, name
    # The cat's colours (a wooden figure: brown) on the map, in every view.
    for panel in range(3):
        pixels = panel_pixels(out / 'textured_map.png', panel, 160)
        hsv = cv2.cvtColor(pixels.reshape(-1, 1, 3), cv2.COLOR_BGR2HSV).reshape(-1, 3)
        coloured = (hsv[:, 1] > 60) & (hsv[:, 2] > 40)
        assert np.count_nonzero(coloured) > 30, panel
        # Warm colours (red to yellow), not the blue the channels swapped would give.
        hues = hsv[coloured, 0].astype(int)
        assert np.mean((hues < 30) | (hues > 170)) > 0.8, np.median(hues)


def test_render_map_says_why_there_are_no_stereo_pictures(cat_maps, tmp_path, capsys):
    # No camera_pose (only the mapping file), no map colours: two notes, the rest drawn.
    out = tmp_path / 'plain'
    written, err = run_render(capsys, cat_maps['plain'], '--bag', CAT, '--config', STATIC,
                              '--output', out)
    notes = [line for line in err.splitlines() if 'note:' in line]
    assert len(notes) == 2, err
    assert 'no stereo_points.png' in notes[0] and 'camera_pose' in notes[0]
    assert 'no textured_map.png' in notes[1] and 'no camera colours' in notes[1]
    names = {line.rsplit('/', 1)[-1] for line in written}
    assert not names & {'textured_map.png', *STEREO_PICTURES}
    assert {'raw_points.png', 'map_above_0.8.png', 'figure.png'} <= names
    # The map's colours alone give the textured map (no bag needed).
    written, err = run_render(capsys, cat_maps['coloured'], '--output', tmp_path / 'map')
    assert 'note:' not in err, err
    names = {line.rsplit('/', 1)[-1] for line in written}
    assert 'textured_map.png' in names and not names & set(STEREO_PICTURES)
    # A bag without images, with the rig's config.
    written, err = run_render(capsys, cat_maps['sphere'], '--bag', cat_maps['sphere_bag'],
                              '--config', STATIC, '--config', STEREO, '--output',
                              tmp_path / 'sphere')
    assert 'the bag holds no stereo pair' in err, err
    assert not {line.rsplit('/', 1)[-1] for line in written} & set(STEREO_PICTURES)
