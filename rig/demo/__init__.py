"""What `rig demo` builds around the ordinary steps (capture, record, align, validate, render): the
disk it will take (disk.py), and for `rig demo --gopro` the rig of GoPro emulators filming the
scene and the alignment's comparison with the simulator's truth (gopro.py). The steps themselves
are the library functions the commands call; `rig.commands.demo` runs them and says what they found.
"""
