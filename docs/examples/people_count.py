"""people_count: how many people each frame's detections hold (the template of docs/writing-a-node.md)."""

from followbus.bus.node import In, Node, Out
from followbus.bus.schemas import Tick
from followbus.msgs.perception import Detections


class PeopleCount(Node):
    INPUTS = {"detections": In(Detections, required=True)}
    OUTPUTS = {"count": Out(Tick)}

    def on_frame(self, frame_seq, inputs):
        self.publish("count", Tick(value=len(inputs["detections"].boxes)))


NODE = PeopleCount
