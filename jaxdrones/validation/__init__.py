"""The simulator held against real Crazyflies (docs/validation.md): readers of public data (`readers`: a thrust
stand's sweep, Neural-Swarm's flights, the firmware's uSD logs) and the thrust map scored and fitted against a stand
(`thrust`)."""
