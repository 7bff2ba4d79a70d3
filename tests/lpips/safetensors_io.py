"""Minimal safetensors writer shared by the LPIPS scripts (no dependency beyond numpy).

Layout: 8-byte little-endian header length, JSON header (padded with spaces to a multiple of
8 bytes), then each tensor's raw little-endian bytes in order.
"""
import json

import numpy as np

DTYPES = {
    np.dtype(np.uint8): "U8",
    np.dtype(np.float16): "F16",
    np.dtype(np.float32): "F32",
    np.dtype(np.float64): "F64",
}


def write_safetensors(path, tensors, metadata=None):
    """Writes a dict name -> numpy array (insertion order kept) and string metadata."""
    header = {}
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in metadata.items()}
    chunks = []
    offset = 0
    for name, array in tensors.items():
        array = np.ascontiguousarray(array)
        dtype = DTYPES[array.dtype]
        data = array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes()
        header[name] = {
            "dtype": dtype,
            "shape": list(array.shape),
            "data_offsets": [offset, offset + len(data)],
        }
        chunks.append(data)
        offset += len(data)
    encoded = json.dumps(header, separators=(",", ":")).encode()
    encoded += b" " * (-len(encoded) % 8)
    with open(path, "wb") as file:
        file.write(len(encoded).to_bytes(8, "little"))
        file.write(encoded)
        for data in chunks:
            file.write(data)
