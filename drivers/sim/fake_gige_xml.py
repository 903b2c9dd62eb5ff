"""The GenICam XML of the fake GigE camera: the library's own plus the station's features.

The XML is built at run time from the installed libaravis's fake-camera XML
(``arv_fake_camera_get_genicam_xml``); :func:`patch_genicam_xml` adds ``ExposureTime`` (µs),
``Gain`` (dB, an IEEE double register), ``DeviceTemperature`` (°C), ``DeviceSerialNumber``
and a ``Mono12`` ``PixelFormat`` entry, on the registers of :mod:`drivers.sim.fake_gige_lib`.
"""

from __future__ import annotations

import ctypes
import xml.etree.ElementTree as ET

from drivers.sim.fake_gige_lib import MONO12, REG_GAIN_DB, REG_TEMPERATURE_C, aravis_lib

GENAPI_NS = "http://www.genicam.org/GenApi/Version_1_0"
XSI_NS = "http://www.w3.org/2001/XMLSchema-instance"


def library_genicam_xml() -> str:
    """The fake camera XML shipped in the installed libaravis (unpatched)."""
    lib = aravis_lib()
    cam = lib.arv_fake_camera_new(b"XMLPROBE")
    try:
        size = ctypes.c_size_t()
        ptr = lib.arv_fake_camera_get_genicam_xml(cam, ctypes.byref(size))
        return ctypes.string_at(ptr, size.value).decode("utf-8")
    finally:
        lib.g_object_unref(cam)


def _genapi_tag(tag: str) -> str:
    """``tag`` qualified with the GenApi namespace, as ElementTree names it."""
    return f"{{{GENAPI_NS}}}{tag}"


def _add_element(
    parent: ET.Element, tag: str, text: str | None = None, **attrib: str
) -> ET.Element:
    """Append a GenApi child ``tag`` to ``parent``, with ``text`` if given; return it."""
    el = ET.SubElement(parent, _genapi_tag(tag), attrib)
    if text is not None:
        el.text = text
    return el


def _float_feature(
    name: str, description: str, value_node: str, limits: tuple[float, float], unit: str
) -> ET.Element:
    """A standard ``Float`` feature reading ``value_node``, ``limits`` (min, max) in ``unit``."""
    feature = ET.Element(_genapi_tag("Float"), {"Name": name, "NameSpace": "Standard"})
    _add_element(feature, "Description", description)
    _add_element(feature, "pValue", value_node)
    _add_element(feature, "Min", repr(float(limits[0])))
    _add_element(feature, "Max", repr(float(limits[1])))
    _add_element(feature, "Unit", unit)
    return feature


def _double_register(name: str, address: int, access_mode: str) -> ET.Element:
    """A custom ``FloatReg``: a big-endian IEEE double (8 bytes) at ``address`` of the device."""
    reg = ET.Element(_genapi_tag("FloatReg"), {"Name": name, "NameSpace": "Custom"})
    _add_element(reg, "Address", hex(address))
    _add_element(reg, "Length", "8")
    _add_element(reg, "AccessMode", access_mode)
    _add_element(reg, "pPort", "Device")
    _add_element(reg, "Endianess", "BigEndian")
    return reg


def patch_genicam_xml(
    xml: str,
    *,
    exposure_limits_us: tuple[float, float] = (10.0, 1_000_000.0),
    gain_limits_db: tuple[float, float] = (0.0, 24.0),
) -> str:
    """Add the SFNC features the station needs to the library's fake-camera XML.

    Adds (when missing) ``DeviceSerialNumber``, ``ExposureTime`` (Float, µs, on the fake's
    exposure register), ``Gain`` (Float, dB, on an IEEE double register),
    ``DeviceTemperature`` (Float, °C, read-only, set with
    :meth:`FakeGigECamera.set_temperature_c`), and a ``Mono12`` ``PixelFormat`` entry.
    Existing nodes are left alone.
    """
    ET.register_namespace("", GENAPI_NS)
    ET.register_namespace("xsi", XSI_NS)
    root = ET.fromstring(xml)
    by_name = {el.get("Name"): el for el in root if el.get("Name")}
    port = next((el for el in root if el.tag == _genapi_tag("Port")), None)
    insert_at = list(root).index(port) if port is not None else len(root)
    new: list[ET.Element] = []

    def category_add(category: str, feature: str) -> None:
        cat = by_name.get(category)
        if cat is not None and not any(p.text == feature for p in cat):
            _add_element(cat, "pFeature", feature)

    if "DeviceSerialNumber" not in by_name:
        reg = ET.Element(
            _genapi_tag("StringReg"), {"Name": "DeviceSerialNumber", "NameSpace": "Standard"}
        )
        _add_element(reg, "Address", "0xd8")
        _add_element(reg, "Length", "16")
        _add_element(reg, "AccessMode", "RO")
        _add_element(reg, "pPort", "Device")
        new.append(reg)
        category_add("DeviceControl", "DeviceSerialNumber")

    if "ExposureTime" not in by_name:
        new.append(
            _float_feature(
                "ExposureTime",
                "Exposure time, in microseconds.",
                "ExposureTimeAbsConverter",
                exposure_limits_us,
                "us",
            )
        )
        category_add("AcquisitionControl", "ExposureTime")

    if "Gain" not in by_name:
        new += [
            _float_feature("Gain", "Analog gain, in dB.", "GainDbRegister", gain_limits_db, "dB"),
            _double_register("GainDbRegister", REG_GAIN_DB, "RW"),
        ]
        category_add("AnalogControl", "Gain")
        category_add("Root", "AnalogControl")

    if "DeviceTemperature" not in by_name:
        new += [
            _float_feature(
                "DeviceTemperature",
                "Temperature of the sensor, in degrees Celsius.",
                "DeviceTemperatureRegister",
                (-40.0, 150.0),
                "C",
            ),
            _double_register("DeviceTemperatureRegister", REG_TEMPERATURE_C, "RO"),
        ]
        category_add("DeviceControl", "DeviceTemperature")

    pixel_format = by_name.get("PixelFormat")
    if pixel_format is not None:
        entries = [e for e in pixel_format if e.tag == _genapi_tag("EnumEntry")]
        if not any(e.get("Name") == "Mono12" for e in entries):
            entry = ET.Element(
                _genapi_tag("EnumEntry"), {"Name": "Mono12", "NameSpace": "Standard"}
            )
            _add_element(entry, "Value", str(MONO12))
            pos = list(pixel_format).index(entries[-1]) + 1 if entries else 0
            pixel_format.insert(pos, entry)

    for offset, el in enumerate(new):
        root.insert(insert_at + offset, el)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode")
