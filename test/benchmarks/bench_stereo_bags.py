"""Disparity of the bundled bags' stereo pairs against their true disparity, on the object.

    .venv/bin/python test/benchmarks/bench_stereo_bags.py

For each bundled bag: the pair and camera_infos from the bag, the true disparity from its
truth file; density (object pixels with a disparity) and bad-2 (of those, |d - d_true| > 2 px)
for config/stereo.yaml's setting and the alternatives it was chosen over, and bare OpenCV
SGBM with its defaults (same disparity range), side by side. The scores are
``inhand_tools.stereo_quality.disparity_scores``, which ``map_metrics`` reports for a bag's
shot.
"""

from __future__ import annotations

import cv2
import numpy as np
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, Image

from inhand_common.bag_source import BagSource
from inhand_common.ground_truth import load_truth
from inhand_stereo.camera_model import CameraModel
from inhand_stereo.image_encoding import image_to_array
from inhand_stereo.stereo_pipeline import StereoPipeline
from inhand_tools.stereo_quality import disparity_scores


def load(bag: str):
    """(left image, right image, left model, right model) of a bag's stereo pair."""
    messages = {}
    with BagSource(bag) as source:
        wanted = {topic for topic in source.topics if topic.startswith('stereo/')}
        for topic, _, raw in source.messages(wanted):
            kind = Image if topic.endswith('image_raw') else CameraInfo
            messages[topic] = deserialize_message(raw, kind)

    def image(side):
        m = messages[f'stereo/{side}/image_raw']
        return image_to_array(m.encoding, m.height, m.width, m.step, m.data)

    def model(side):
        m = messages[f'stereo/{side}/camera_info']
        return CameraModel.from_fields(m.width, m.height, m.k, m.d, m.r, m.p,
                                       m.distortion_model, side)

    return image('left'), image('right'), model('left'), model('right')


VARIANTS = {
    'BM, stereo_image_proc defaults': dict(stereo_algorithm=0),
    'SGBM window 7': dict(stereo_algorithm=1, correlation_window_size=7),
    'SGBM window 5': dict(stereo_algorithm=1, correlation_window_size=5),
    'SGBM window 5, median 5 (config/stereo.yaml)': dict(stereo_algorithm=1,
                                                         correlation_window_size=5,
                                                         median_size=5),
}


def line(bag, name, disparity, valid, truth):
    scores = disparity_scores(disparity, valid, truth.disparity, truth.object_mask)
    print(f'{bag:14s} {name:46s} object density {scores["object_density"]:.3f} bad-2 '
          f'{scores["object_bad2"]:.4f} | image density {scores["image_density"]:.3f} bad-2 '
          f'{scores["image_bad2"]:.4f}')


def main():
    for bag in ('cat_static', 'cat_moving', 'bottle_static'):
        left, right, left_model, right_model = load(f'bags/{bag}')
        truth = load_truth(f'bags/{bag}.truth.npz').stereo
        for name, values in VARIANTS.items():
            pipeline = StereoPipeline({**values, 'min_disparity': 48, 'disparity_range': 112})
            shot = pipeline.process(0, left, right, 'rgb8', left_model, right_model)
            line(bag, name, shot.disparity.disparity, shot.disparity.valid, truth)
        grey = [cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) for image in (left, right)]
        bare = cv2.StereoSGBM_create(minDisparity=48, numDisparities=112).compute(*grey)
        bare = bare.astype(np.float32) / 16
        line(bag, 'bare OpenCV SGBM, its defaults', bare, bare >= 48, truth)


if __name__ == '__main__':
    main()
