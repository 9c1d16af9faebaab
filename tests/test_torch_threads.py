"""torch's thread count for a block (`reachwatch.systems.torch_threads`): blocks in
several threads at once, interleaved in every order, give back the count found before
the first, never another block's."""

import threading

import pytest
import torch

from reachwatch.systems.torch_threads import torch_threads


def test_overlapping_blocks_in_two_threads_give_the_first_count_back():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
        seen = {}

        def a():                # in first, out first: the count stays 1 for b
            with torch_threads(1):
                a_in.set()
                b_in.wait(5)
                seen["a"] = torch.get_num_threads()
            a_out.set()

        def b():
            a_in.wait(5)
            with torch_threads(1):
                b_in.set()
                a_out.wait(5)
                seen["b"] = torch.get_num_threads()

        threads = [threading.Thread(target=f) for f in (a, b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(10)
        assert seen == {"a": 1, "b": 1}
        assert torch.get_num_threads() == 2             # the count before, not b's 1
        with torch_threads(0):                           # 0: as it is
            assert torch.get_num_threads() == 2
        with torch_threads(1):
            with pytest.raises(RuntimeError, match=r"torch_threads\(2\) while another block "
                                                   r"runs torch on 1 threads"):
                with torch_threads(2):
                    pass
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
