from setuptools import setup

package_name = "lidar_quality_training"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name, f"{package_name}.lmd", f"{package_name}.lms", f"{package_name}.mimo"],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="lidar_quality maintainers",
    maintainer_email="lidar-quality@example.com",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "lmd-train = lidar_quality_training.lmd.train:main",
            "lmd-eval = lidar_quality_training.lmd.evaluate:main",
            "lms-train = lidar_quality_training.lms.train:main",
            "lms-eval = lidar_quality_training.lms.evaluate:main",
            "mimo-train = lidar_quality_training.mimo.train:main",
            "mimo-eval = lidar_quality_training.mimo.evaluate:main",
            "lmd-adapt = lidar_quality_training.lmd.adapt:main",
            "lms-adapt = lidar_quality_training.lms.adapt:main",
            "mimo-adapt = lidar_quality_training.mimo.adapt:main",
        ],
    },
)
