"""Map sharing: the thesis codec, the wire format of map messages (and later MTP, transport)."""
