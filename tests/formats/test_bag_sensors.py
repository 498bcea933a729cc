"""Bag readers for images and camera_info: bags written here (ROS1 and ROS2) carrying the real
KITTI 00 stereo pair and that sequence's projection matrices."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from pancam_graph.errors import InputError
from pancam_graph.formats.rosbag import read_images, read_stereo_camera_info

pytestmark = pytest.mark.real_data

REAL = Path(__file__).parents[1] / "data" / "real"
BAG = REAL / "robot_localization" / "test1.bag"
PAIR = REAL / "kitti00_stereo_pair"
# KITTI odometry sequence 00, calib.txt P0 and P1 (rectified; P1[0, 3] = -fx * baseline)
P0 = [718.856, 0, 607.1928, 0, 0, 718.856, 185.2157, 0, 0, 0, 1, 0]
P1 = [718.856, 0, 607.1928, -386.1448, 0, 718.856, 185.2157, 0, 0, 0, 1, 0]


def _stamp(typestore, t: float):
    return typestore.types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))


def _header(typestore, t: float, ros1: bool):
    header = typestore.types["std_msgs/msg/Header"]
    return header(seq=0, stamp=_stamp(typestore, t), frame_id="cam") if ros1 else header(stamp=_stamp(typestore, t),
                                                                                        frame_id="cam")


def _camera_info(typestore, t: float, projection: list[float], ros1: bool):
    info = typestore.types["sensor_msgs/msg/CameraInfo"]
    roi = typestore.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                             do_rectify=False)
    arrays = dict(D=np.zeros(5), K=np.array(projection).reshape(3, 4)[:, :3].ravel(), R=np.eye(3).ravel(),
                  P=np.array(projection, dtype=float))
    if not ros1:
        arrays = {k.lower(): v for k, v in arrays.items()}
    return info(header=_header(typestore, t, ros1), height=376, width=1241, distortion_model="plumb_bob",
                binning_x=0, binning_y=0, roi=roi, **arrays)


def _write_bag(path: Path, ros1: bool, encoding: str = "mono8") -> tuple[np.ndarray, np.ndarray]:
    """Left as sensor_msgs/Image, right as CompressedImage (PNG), and both camera_infos."""
    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    left = cv2.imread(str(PAIR / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(PAIR / "right.png"), cv2.IMREAD_GRAYSCALE)
    image = typestore.types["sensor_msgs/msg/Image"]
    compressed = typestore.types["sensor_msgs/msg/CompressedImage"]
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), typestore.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, serialize = Writer(path, version=8), typestore.serialize_cdr
    with writer:
        topics = {}
        for topic, kind in (("/left/image_rect", image), ("/right/image_rect/compressed", compressed),
                            ("/left/camera_info", typestore.types["sensor_msgs/msg/CameraInfo"]),
                            ("/right/camera_info", typestore.types["sensor_msgs/msg/CameraInfo"])):
            topics[topic] = writer.add_connection(topic, kind.__msgtype__, typestore=typestore)
        for t in (100.0, 100.1):
            messages = {
                "/left/image_rect": image(header=_header(typestore, t, ros1), height=left.shape[0],
                                          width=left.shape[1], encoding=encoding, is_bigendian=0,
                                          step=left.shape[1], data=left.ravel()),
                "/right/image_rect/compressed": compressed(header=_header(typestore, t, ros1), format="png",
                                                           data=np.frombuffer(cv2.imencode(".png", right)[1],
                                                                              dtype=np.uint8)),
                "/left/camera_info": _camera_info(typestore, t, P0, ros1),
                "/right/camera_info": _camera_info(typestore, t, P1, ros1),
            }
            for topic, message in messages.items():
                writer.write(topics[topic], int(t * 1e9), serialize(message, message.__msgtype__))
    return left, right


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_images_and_camera_info_round_trip_through_a_bag(tmp_path, ros1):
    bag = tmp_path / ("stereo.bag" if ros1 else "stereo")
    left, right = _write_bag(bag, ros1)
    lefts = list(read_images(bag, "/left/image_rect"))
    rights = list(read_images(bag, "/right/image_rect/compressed"))
    assert [s.time_s for s in lefts] == pytest.approx([100.0, 100.1])
    assert all(np.array_equal(s.image, left) for s in lefts)
    assert all(np.array_equal(s.image, right) for s in rights)  # PNG is lossless
    stereo = read_stereo_camera_info(bag, "/left/camera_info", "/right/camera_info")
    assert stereo.baseline_m == pytest.approx(0.5371657, abs=1e-7)  # the sequence's published baseline
    assert (stereo.camera.fx, stereo.camera.cx, stereo.camera.width) == (718.856, 607.1928, 1241)


def test_bad_image_bags_name_topic_and_message(tmp_path):
    bag = tmp_path / "yuv.bag"
    _write_bag(bag, ros1=True, encoding="yuv422")
    with pytest.raises(InputError, match=r"yuv\.bag: /left/image_rect message 0: image encoding 'yuv422'"):
        list(read_images(bag, "/left/image_rect"))
    with pytest.raises(InputError, match="2 image topics .*choose one"):
        list(read_images(bag, None))
    with pytest.raises(InputError, match="/left/camera_info is not an Image or CompressedImage topic"):
        list(read_images(bag, "/left/camera_info"))
    with pytest.raises(InputError, match="Tx = 0.0: expected -fx \\* baseline < 0"):
        read_stereo_camera_info(bag, "/right/camera_info", "/left/camera_info")  # swapped
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    with pytest.raises(InputError, match="truncated.bag"):
        list(read_images(truncated, "/left/image_rect"))
