"""gym-pybullet-drones' utilities: enums, ``Logger``, ``sync`` and ``str2bool``."""
