"""Other simulators' interfaces on the jaxdrones physics, for code written against them.

`jaxdrones.compat.gym_pybullet_drones`: gym-pybullet-drones' classes (``HoverAviary``, ``MultiHoverAviary``,
``CtrlAviary``, ``DSLPIDControl``, ``Logger``, the enums) with their keyword names, constants, observations, rewards
and ``info``, under the same module paths: replace ``gym_pybullet_drones`` by ``jaxdrones.compat.gym_pybullet_drones``
in a script's imports. docs/migrating.md lists every difference that remains.
"""
