"""MAVLink 2 message signing of the simulated vehicles, as ArduPilot does it once a key is set.

With a key (``swarmplan sim --signing-key-file PATH`` or ``$SWARMPLAN_SIGNING_KEY``; 32 raw bytes
or 64 hex characters, never a command-line value; a key file that does not exist is made with a
new key for the mission, mode 0600, for the daemon to read), every vehicle:

* signs everything it sends (each component its own stream, timestamps from the wall clock);
* refuses every frame that is unsigned, wrongly signed, or a replay (a timestamp not newer than
  the last accepted one of its stream ``(link id, system, component)``, or a new stream more
  than a minute behind the clock). Refused frames are counted (``unsigned_refused``,
  ``bad_signatures``, ``replays_refused``) and never reach a handler: a spoofed DO_REPOSITION or
  SET_MODE changes nothing and gets no ACK.
* accepts unsigned only RADIO_STATUS and RADIO, like ArduPilot's ``accept_unsigned_callback``
  (a telemetry radio cannot sign). An unsigned HEARTBEAT is refused too, so a stranger cannot
  hold off the GCS failsafe. ArduPilot also accepts everything on its USB port (channel 0);
  the simulator has no such port.

The signature is checked before the stream timestamp is recorded (pymavlink's own check records
it first, so one forged frame with a far-future timestamp would lock out the real sender).
The key handling and the checker are the ones of ``mavlink_wire/signing.py`` (the MAVLink
signing spec, one implementation for both sides); this module only wires them into the
simulated vehicles. (``mavlink_bridge`` never imports ``sim_gateway``; the other way is fine.)
"""

from __future__ import annotations

from collections.abc import Iterable

from mavlink_wire.signing import (
    KEY_ENV,
    SignatureCheck,
    SigningKeyError,
    load_or_create_key_file,
    load_signing_key,
    sign_outgoing,
)
from sim_gateway.mavlink_endpoint import ComponentSender, DatagramParser

__all__ = [
    "KEY_ENV",
    "SignatureCheck",
    "SigningKeyError",
    "enable_signing",
    "load_or_create_key_file",
    "load_signing_key",
]


def enable_signing(
    parser: DatagramParser, senders: Iterable[ComponentSender], key: bytes
) -> SignatureCheck:
    """Make ``senders`` (each component of each vehicle) sign what they send, and ``parser``
    (the vehicles' one way in) refuse what is not signed."""
    check = SignatureCheck(key)
    parser.signature_check = check
    for sender in senders:
        sign_outgoing(sender.mav, key, link_id=0)
    return check
