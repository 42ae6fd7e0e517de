"""cosy: CosyPose as a command-line pipeline over BOP datasets.

Units: millimetres for every length that crosses a file or function boundary unless a name
says otherwise. Poses are 4x4 homogeneous matrices named ``T_a_b`` (maps points of frame b into
frame a). Cameras follow OpenCV/BOP: x right, y down, looking along +z.
"""

__version__ = "0.1.0"
