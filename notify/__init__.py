"""``voxelwatch notify``: alarms delivered where the people who watch already look.

A zenoh reader (:mod:`notify.service`) hears events, tracks and camera
status, keeps every event of a chosen kind in an outbox on disk
(:mod:`notify.outbox`) once per channel, and one thread per channel
(:mod:`notify.channel`) delivers it: MQTT with Home Assistant
discovery (:mod:`notify.mqtt`), webhooks (:mod:`notify.webhook`)
and e-mail (:mod:`notify.mail`). An event stays in the outbox until
its channel confirms it, across restarts of the notifier, the broker or the
network: at least once, every delivery carrying the event id so that
receivers drop repeats. :mod:`notify.people` holds the logic of
person and camera states and the alarm texts; :mod:`notify.cli` the
command line.
"""
