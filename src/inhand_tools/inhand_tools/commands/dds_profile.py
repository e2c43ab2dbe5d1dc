"""``dds_profile``: the Fast DDS profile the graph runs with, for a camera driver to use too.

    dds_profile [--output FILE]

Every program of the graph runs with this profile (``inhand_common/dds_profile.py``): a
32 MiB shared-memory segment, so that a 640x480 rgb8 image (921,600 bytes) reaches another
process whole, also best effort, and UDPv4 with 4 MiB socket buffers. Fast DDS uses the
*publisher's* segment, so a camera driver in its own process needs it too:

    dds_profile --output ~/inhand_fastdds.xml
    FASTRTPS_DEFAULT_PROFILES_FILE=~/inhand_fastdds.xml ros2 run <camera driver> ...

Prints the XML on standard output, or writes it to FILE (whole or not at all).
"""

from __future__ import annotations

import sys

from inhand_common.atomic_file import atomic_write
from inhand_common.cli_types import command_parser
from inhand_common.dds_profile import profile_xml

PROG = 'dds_profile'


def main(argv: list[str] | None = None) -> int:
    parser = command_parser(PROG, __doc__)
    parser.add_argument('--output', help='write the profile to this file')
    args = parser.parse_args(argv)
    xml = profile_xml()
    if args.output is None:
        sys.stdout.write(xml)
        return 0
    try:
        with atomic_write(args.output) as out:
            out.write(xml.encode())
    except OSError as error:
        print(f'{PROG}: cannot write {args.output}: {error.strerror} ({error.filename})',
              file=sys.stderr)
        return 1
    print(f'{PROG}: wrote {args.output}; run the camera driver with '
          f'FASTRTPS_DEFAULT_PROFILES_FILE={args.output}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
