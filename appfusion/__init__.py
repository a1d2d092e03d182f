"""appfusion: interactive appearance acquisition with a consumer depth camera.

The system of Wu & Zhou, "AppFusion: Interactive Appearance Acquisition Using a Kinect Sensor"
(Computer Graphics Forum 2015). Importing this package is cheap: heavy modules (Open3D, Qt) are
imported by the modules that need them.
"""

__version__ = "0.1.0"
