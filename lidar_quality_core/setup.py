from setuptools import setup

package_name = "lidar_quality_core"

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
    description="Shared computation core of the lidar quality suite (no rclpy).",
    license="Apache-2.0",
)
