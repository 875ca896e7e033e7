"""Materials: SVBRDF texture maps in the OpenSVBRDF contract (the one owner of that folder format), the
built-in procedural samples, and EXR files."""
