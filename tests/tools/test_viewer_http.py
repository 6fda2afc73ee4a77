"""tools/viewer_http.py: json_safe keeps /status.json strict JSON whatever the node's stats map holds (the HTTP
endpoints themselves are tested through the Viewer in test_viewer.py)."""

from __future__ import annotations

import json

from tools import viewer_http as viewer


def test_status_json_survives_a_stats_map_nested_a_thousand_deep():
    """msgpack decodes nesting up to ~1000 levels; such a stats map (a hostile publisher) made every /status.json
    request fail with a RecursionError and a 3000-line traceback on the viewer's stderr."""
    import msgpack

    deep: object = None
    for _ in range(990):
        deep = [deep]
    stats = msgpack.unpackb(msgpack.packb({"v": 1, "events_per_s": 2.0, "deep": deep}))
    body = json.loads(json.dumps(viewer.json_safe({"node": stats})))
    assert body["node"]["events_per_s"] == 2.0 and body["node"]["v"] == 1
    level, depth = body["node"]["deep"], 0
    while isinstance(level, list):
        level, depth = level[0], depth + 1
    assert isinstance(level, str) and depth < 990  # cut off, said in a string
