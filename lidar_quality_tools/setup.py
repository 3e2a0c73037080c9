from setuptools import setup

package_name = "lidar_quality_tools"

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
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    entry_points={
        "console_scripts": ["demo = lidar_quality_tools.demo:main",
                            "process_bag = lidar_quality_tools.process:main",
                            "process_bags = lidar_quality_tools.fleet:main",
                            "fleet_review = lidar_quality_tools.fleet_review:main"],
    },
)
