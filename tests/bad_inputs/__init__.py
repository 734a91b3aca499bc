"""Generators of bad inputs for the reliability tests (small real files made on the fly).

- :mod:`.drives`: synthetic orchard drives written as ROS1/ROS2 bags, with faults
  (dropouts, empty scans, NaN points, repeated or backwards stamps, missing sensors);
- :mod:`.corrupt`: cut files short, overwrite bytes;
- :mod:`.clouds`: LAS files with broken headers or no points;
- :mod:`.drone`: folders of geotagged drone JPEGs with wrong files;
- :mod:`.presets`: preset TOML files with unknown keys, wrong types, values out of range;
- :mod:`.catalogue`: every case with its expected behaviour (docs/RELIABILITY.md).
"""
