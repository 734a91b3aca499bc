"""The XMP packet a DJI drone writes into each photo: gimbal and flight attitude, altitudes.

Tags of the ``drone-dji`` namespace as DJI's photos carry them (``GimbalYawDegree``,
``GimbalPitchDegree``, ``GimbalRollDegree``, ``FlightYawDegree``, ``FlightPitchDegree``,
``FlightRollDegree``, ``RelativeAltitude``, ``AbsoluteAltitude``), signed text with two
decimals. The angles follow :mod:`canopy_kit.core.gimbal`.
"""

from __future__ import annotations

DJI_NAMESPACE = "http://www.dji.com/drone-dji/1.0/"
XMP_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"  # the APP1 segment's identifier


def dji_xmp(
    gimbal: tuple[float, float, float],
    flight: tuple[float, float, float],
    relative_altitude: float,
    absolute_altitude: float,
) -> bytes:
    """The XMP packet (UTF-8) of one photo: gimbal and flight (yaw, pitch, roll) in degrees,
    altitudes in metres above take-off and above the ellipsoid."""
    tags = {
        "AbsoluteAltitude": absolute_altitude,
        "RelativeAltitude": relative_altitude,
        "GimbalRollDegree": gimbal[2],
        "GimbalYawDegree": gimbal[0],
        "GimbalPitchDegree": gimbal[1],
        "FlightRollDegree": flight[2],
        "FlightYawDegree": flight[0],
        "FlightPitchDegree": flight[1],
    }
    attributes = "\n".join(f'   drone-dji:{k}="{v:+.2f}"' for k, v in tags.items())
    text = (
        "<?xpacket begin='\ufeff' id='W5M0MpCehiHzreSzNTczkc9d'?>\n"
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        '  <rdf:Description rdf:about="DJI Meta Data"\n'
        f'   xmlns:drone-dji="{DJI_NAMESPACE}"\n'
        f"{attributes}>\n"
        "  </rdf:Description>\n"
        " </rdf:RDF>\n"
        "</x:xmpmeta>\n"
        "<?xpacket end='w'?>"
    )
    return text.encode("utf-8")
