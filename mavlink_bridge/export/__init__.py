"""Waypoint and map files of a mission for ground stations (QGC WPL 110, QGroundControl .plan,
GeoJSON, KML), made from its result. Imports no other sub-package of ``mavlink_bridge``."""
