"""Flight viewer: a rollout as one self-contained HTML file that plays offline, or as a GIF/MP4 through the JAX
cameras.

`write_html` records a `Flight` (positions and attitudes of every drone of one world or many, the scene's
obstacles and gates, and the onboard camera images when the env has cameras) with viser's scene serializer and
writes viser's static client with the recording embedded: one ``.html`` file that opens from ``file://`` with no
server and no network, with play/pause, a time slider, playback speed, trails behind the drones and a 3D view to
orbit. It needs viser (the ``viewer`` extra: ``pip install ".[viewer]"`` from a clone; viser's
``ViserServer.get_scene_serializer`` and ``StateSerializer.as_html``, https://viser.studio): the scene is built in
a viser server bound to localhost, which no client ever joins, and recorded message by message.

`write_video` draws the same flight from a chase or fixed camera with the JAX ray caster
(`jaxdrones.cameras.render`, no PyBullet) and writes a GIF or MP4 (`jaxdrones.io.video.VideoWriter`).

    import jaxdrones as jd
    from jaxdrones.viz import Flight, write_html

    flight = Flight.from_states(env, states)      # states: EnvState with a leading time axis (rollout_policy)
    write_html("flight.html", flight)

Frames: positions are m in the world frame, z up; quaternions (x, y, z, w) rotate body to world, as everywhere in
jaxdrones (`jaxdrones.DroneState`).

The package: `jaxdrones.viz.flight` (the `Flight` record and what both views take from it),
`jaxdrones.viz.html` (`write_html`), `jaxdrones.viz.video` (`write_video`); each name is also here.
"""

from jaxdrones.viz.flight import CF2X_ARM, DRONE_COLORS, Colors, Flight, View, flight_data
from jaxdrones.viz.html import VIEW_EPISODES, VIEW_FOV, VIEWER_INSTALL, viewer_available, write_html
from jaxdrones.viz.video import SKY_RGB, VIDEO_CAMERAS, write_video

__all__ = [
    "CF2X_ARM",
    "DRONE_COLORS",
    "SKY_RGB",
    "VIDEO_CAMERAS",
    "VIEWER_INSTALL",
    "VIEW_EPISODES",
    "VIEW_FOV",
    "Colors",
    "Flight",
    "View",
    "flight_data",
    "viewer_available",
    "write_html",
    "write_video",
]
