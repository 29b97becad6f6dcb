"""The server's threads are named for the operating system too (what top -H and the CPU
benchmark read)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from server.threads import name_thread


def test_a_pool_thread_carries_its_name_to_the_os() -> None:
    with ThreadPoolExecutor(1, thread_name_prefix="encode", initializer=name_thread) as pool:
        tid = pool.submit(threading.get_native_id).result()
        assert Path(f"/proc/self/task/{tid}/comm").read_text().strip() == "encode_0"
    long = threading.Thread(target=name_thread, name="a-name-longer-than-15-bytes")
    long.start()
    long.join()  # cut to what Linux keeps, not refused
