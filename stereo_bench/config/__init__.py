"""The rig file: its schema, the bounds every input is held to, and the bounded YAML reader.

* ``schema``: the pydantic models of every section (cameras, studio, pattern, trajectory,
  environment, calibration, renderer), ``parse_rig`` / ``load_rig`` and ``describe`` (a
  validation error in words);
* ``bounds``: the upper bounds (image size, counts, focal length, distances...) and
  ``ConfigError``;
* ``yaml_reader``: YAML read with unique keys and aliases measured before anything is built;
* ``environments``: the imaging presets an ``environment.kind`` names.
"""
