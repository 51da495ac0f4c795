"""Zenoh access control for a site: who may publish, declare, subscribe and query what.

Built from the site's prefix and camera ids; subjects are known by the common
name of their certificate (:func:`common.certs.common_name`). Everything not
allowed here is denied. A router checks what each host sends it (``ingress``)
and what it forwards to each host (``egress``), so both flows are listed:

| host          | sends (ingress)                                              | receives (egress)                         |
|---------------|--------------------------------------------------------------|-------------------------------------------|
| camera <id>   | puts ``<p>/cam/<id>/mask``; token ``<p>/alive/cam/<id>``;    | ``<p>/cam/<id>/hold`` and ``look`` samples |
|               | subscribes ``<p>/cam/<id>/hold``, ``<p>/cam/<id>/look``      |                                           |
| fusion        | puts tracks, events, status, every camera's hold and look;   | masks, liveliness, history queries        |
|               | token ``<p>/alive/fusion``; the history queryable and its    |                                           |
|               | replies; subscribes masks, liveliness of ``<p>/alive/**``    |                                           |
| reader        | subscribes tracks, events, status and masks; queries the     | tracks, events, status, masks, replies    |
|               | history and ``<p>/ack/<id>``; liveliness of ``<p>/alive/**`` |                                           |

Each host also hears of the subscribers and queryables it sends to (a
publisher sends only once it knows of a subscriber). zenoh allows a message
when a rule's key expression includes the message's whole key expression, so
the fusion server's ``<p>/cam/*/mask`` subscription reaches a camera through
a rule on ``<p>/cam/*/mask``. Readers publish nothing: they acknowledge an
alarm with a query on ``<p>/ack/<event id>``, which the fusion server answers
(and it alone publishes the acknowledgement). Readers see the masks (the live
view's installer page draws them: silhouettes, never pixels of video), never
the holds and look requests.
"""

from __future__ import annotations

from collections.abc import Sequence

from common import keys
from common.certs import FUSION, common_name

_BOTH = ["ingress", "egress"]


def site_acl(prefix: str, cameras: Sequence[str], *, readers: Sequence[str] | None = None) -> dict:
    """zenoh's ``access_control`` section for a site (a JSON-ready dict, ``default_permission`` deny).

    ``cameras``: the site's camera ids; ``readers``: the reader names whose certificates
    (``reader-<name>``) may read (default: ``["reader"]``).
    """
    keys.validate_prefix(prefix)
    p = prefix
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []

    def allow(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> str:
        rules.append({"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
                      "key_exprs": key_exprs})
        return rule_id

    for cam in cameras:
        keys.validate_chunk(cam, "camera id")
        own = [keys.hold_key(p, cam), keys.look_key(p, cam)]
        ids = [
            allow(f"camera {cam} publishes its masks", "ingress", ["put", "delete"], [keys.mask_key(p, cam)]),
            allow(f"camera {cam} declares its token", "ingress", ["liveliness_token"], [keys.alive_camera_key(p, cam)]),
            allow(f"camera {cam} subscribes to its holds and looks", "ingress", ["declare_subscriber"], own),
            allow(f"camera {cam} receives its holds and looks", "egress", ["put", "delete"], own),
            # the fusion server subscribes to <p>/cam/*/mask: a declaration is allowed when a rule's key
            # includes its whole key expression, and a camera's publisher sends only once it hears of one
            allow(f"camera {cam} hears who reads masks", "egress", ["declare_subscriber"], [keys.mask_wildcard(p)]),
        ]
        subjects.append({"id": f"camera {cam}", "cert_common_names": [common_name("camera", cam)]})
        policies.append({"id": f"camera {cam}", "rules": ids, "subjects": [f"camera {cam}"]})

    published = [keys.tracks_key(p), keys.events_wildcard(p), keys.status_key(p),
                 f"{p}/cam/*/hold", f"{p}/cam/*/look"]
    history = [f"{keys.history_key(p)}/**", keys.ack_wildcard(p)]
    alive = [f"{p}/alive/**"]
    fusion_ids = [
        allow("fusion publishes", "ingress", ["put", "delete"], published),
        allow("fusion declares its token", "ingress", ["liveliness_token"], [keys.alive_fusion_key(p)]),
        allow("fusion answers the history", "ingress", ["declare_queryable", "reply"], history),
        allow("fusion subscribes to masks", "ingress", ["declare_subscriber"], [keys.mask_wildcard(p)]),
        allow("fusion watches liveliness", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], alive),
        allow("fusion receives masks", "egress", ["put", "delete"], [keys.mask_wildcard(p)]),
        allow("fusion receives liveliness", "egress", ["liveliness_token"], alive),
        allow("fusion receives history queries", "egress", ["query"], history),
        allow("fusion hears who reads", "egress", ["declare_subscriber"], published),
    ]
    subjects.append({"id": "fusion", "cert_common_names": [common_name(FUSION)]})
    policies.append({"id": "fusion", "rules": fusion_ids, "subjects": ["fusion"]})

    read = [keys.tracks_key(p), keys.events_wildcard(p), keys.status_key(p), keys.mask_wildcard(p)]
    reader_ids = [
        allow("readers subscribe", "ingress", ["declare_subscriber"], read),
        allow("readers query the history", "ingress", ["query"], history),
        allow("readers watch liveliness", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], alive),
        allow("readers receive", "egress", ["put", "delete"], read),
        allow("readers receive history replies", "egress", ["reply"], history),
        allow("readers receive liveliness", "egress", ["liveliness_token"], alive),
        allow("readers hear the history", "egress", ["declare_queryable"], history),
    ]
    names = [common_name("reader", r) for r in (readers if readers is not None else ["reader"])]
    subjects.append({"id": "readers", "cert_common_names": names})
    policies.append({"id": "readers", "rules": reader_ids, "subjects": ["readers"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
