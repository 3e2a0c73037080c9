from setuptools import setup

package_name = "lidar_sim"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="lidar_quality maintainers",
    maintainer_email="lidar-quality@example.com",
    description="Synthetic lidar world: street scenes, ray-casting lidar, exact ground truth.",
    license="Apache-2.0",
)
