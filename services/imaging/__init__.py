"""Images as uploaded: decoding (with the JPEG integrity check) and previews."""
