"""Package list for vqtouch: the card's top-level folders installed under one namespace.

setuptools would silently drop any sub-package not listed here, so the list is built
by walking each folder instead of being written by hand.
"""

from setuptools import find_packages, setup

FOLDERS = {
    "core": "vqtouch.core",
    "plugins": "vqtouch.plugins",
    "conditioners": "vqtouch.conditioners",
    "sensors": "vqtouch.sensors",
}

package_dir = {}
packages = []
for folder, dotted in FOLDERS.items():
    package_dir[dotted] = folder
    packages.append(dotted)
    for sub in find_packages(folder):
        packages.append(f"{dotted}.{sub}")
        package_dir[f"{dotted}.{sub}"] = f"{folder}/{sub.replace('.', '/')}"

setup(package_dir=package_dir, packages=packages)
