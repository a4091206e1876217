"""A sensor look in standard MAVLink (docs/mavlink.md, "Sensor looks"): the camera component
(MAV_COMP_ID_CAMERA = 100) reports each look as CAMERA_IMAGE_CAPTURED whose ``file_url`` lists
the detected cells as offsets from the look cell: ``look:dx,dy;dx,dy`` (``look:`` alone when
nothing was detected); a list longer than the 205-character field continues in further messages
of the same ``image_index`` whose text starts ``look+:``. The simulator's camera and the payload
simulator write it, the daemon reads it.
"""

from __future__ import annotations

from collections.abc import Iterable

from mavlink_wire.protocol import mavlink

FILE_URL_CHARS = 205
LOOK_PREFIX = "look:"
LOOK_CONTINUATION_PREFIX = "look+:"


def look_urls(offsets: Iterable[tuple[int, int]]) -> list[str]:
    """The ``file_url`` texts of one look; each fits in 205 characters."""
    entries = [f"{dx},{dy}" for dx, dy in offsets]
    urls: list[str] = []
    current = LOOK_PREFIX
    used = 0  # entries in the current text
    for entry in entries:
        extra = entry if used == 0 else ";" + entry
        if len(current) + len(extra) > FILE_URL_CHARS:
            urls.append(current)
            current, used, extra = LOOK_CONTINUATION_PREFIX, 0, entry
        current += extra
        used += 1
    urls.append(current)
    return urls


def parse_look_url(url: str) -> list[tuple[int, int]]:
    """Offsets in one ``file_url`` text (the inverse of :func:`look_urls`)."""
    for prefix in (LOOK_CONTINUATION_PREFIX, LOOK_PREFIX):
        if url.startswith(prefix):
            return parse_look_offsets(url[len(prefix) :])
    raise ValueError(f"not a look url: {url!r}")


def look_messages(
    offsets: Iterable[tuple[int, int]],
    index: int,
    time_boot_ms: int,
    time_utc_us: int,
    lat_e7: int,
    lon_e7: int,
    alt_amsl_mm: int,
    relative_alt_mm: int,
) -> list[mavlink.MAVLink_camera_image_captured_message]:
    """The CAMERA_IMAGE_CAPTURED messages of one look (docs/mavlink.md, "Sensor looks"): look
    number ``index``, taken at the given position and time, detected cells as ``offsets`` from
    the look cell."""
    return [
        mavlink.MAVLink_camera_image_captured_message(
            time_boot_ms,
            time_utc_us,
            0,
            lat_e7,
            lon_e7,
            alt_amsl_mm,
            relative_alt_mm,
            [1.0, 0.0, 0.0, 0.0],
            index,
            1,
            url.encode(),
        )
        for url in look_urls(offsets)
    ]


def look_part(url: str) -> tuple[bool, str] | None:
    """``(first, offsets text)`` of a look's ``file_url``: whether it is the look's first part
    (``look:``) or a continuation (``look+:``); None for any other text (an ordinary photo)."""
    if url.startswith(LOOK_PREFIX):
        return True, url[len(LOOK_PREFIX) :]
    if url.startswith(LOOK_CONTINUATION_PREFIX):
        return False, url[len(LOOK_CONTINUATION_PREFIX) :]
    return None


def parse_look_offsets(text: str) -> list[tuple[int, int]]:
    """Cells of a look's ``file_url`` after the prefix: ``"0,1;-2,0"`` -> ``[(0, 1), (-2, 0)]``.

    Malformed pairs are skipped (a damaged report must not stop the mission)."""
    offsets: list[tuple[int, int]] = []
    for pair in text.split(";"):
        parts = pair.strip().split(",")
        if len(parts) != 2:
            continue
        try:
            offsets.append((int(parts[0]), int(parts[1])))
        except ValueError:
            continue
    return offsets
