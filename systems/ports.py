"""Helpers for declaring the ports of Python LeafSystems."""

import weakref


def weak_callback(method):
    """``method`` (a bound method of a system) as a callback that holds its system only
    weakly. pydrake never frees a Python LeafSystem whose abstract output port computes
    through a bound method of itself (a cycle through C++ that Python's collector cannot
    see), and with it the whole diagram: 80 MB per taxi world, scene and renderer
    included. The diagram keeps the system alive while the callback can be called::

        self.DeclareAbstractOutputPort("pose", make_value, weak_callback(self._calc_pose))
    """
    ref = weakref.WeakMethod(method)

    def call(*args):
        return ref()(*args)
    return call
