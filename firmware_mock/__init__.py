"""Mock car firmware: the robots' stand-ins, with their own protocol parser (docs/protocol.md).

``wire`` (frame codec) and ``core`` (sans-I/O car rules) are written from the spec, never imported
from ``edge/``; ``firmware`` runs them with timers and faults; ``udp`` is the WiFi car (ESP8266 +
serial line + motor controller), ``can_car`` the CAN FD car; ``cli`` is ``udan-firmware-mock``.
"""
