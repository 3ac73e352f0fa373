"""Decode every message of an MCAP file with the standard Python readers and decoders only
(``mcap`` and ``mcap-protobuf-support``, JSON Schema checked with ``jsonschema``): no
sinewatch code. Prints, as JSON, per channel its encodings and each decoded message (protobuf
messages as dicts, JSON messages as parsed), so a test can compare them with what was sent.

Usage: python decode_mcap.py FILE.mcap
"""

import base64
import json
import sys

import jsonschema
from google.protobuf.json_format import MessageToDict
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory


class JsonDecoderFactory(DecoderFactory):
    """MCAP's ``json`` message encoding (the well-known encodings list it): UTF-8 JSON text.
    The mcap package ships no decoder for it; json.loads is the decoder."""

    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def main(path: str) -> None:
    channels: dict[str, dict] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[ProtobufDecoderFactory(), JsonDecoderFactory()], validate_crcs=True)
        summary = reader.get_summary()
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            out = channels.setdefault(
                f"{channel.id}",
                {
                    "topic": channel.topic,
                    "message_encoding": channel.message_encoding,
                    "schema_name": schema.name,
                    "schema_encoding": schema.encoding,
                    "metadata": dict(channel.metadata),
                    "messages": [],
                    "log_times": [],
                },
            )
            if channel.message_encoding == "protobuf":
                # preserving_proto_field_name: the .proto's names; bytes come back base64
                msg = MessageToDict(
                    decoded, preserving_proto_field_name=True, always_print_fields_with_no_presence=True
                )
                if "raw" in msg:
                    msg["raw"] = base64.b64decode(msg["raw"]).hex()
            else:
                msg = decoded
            if schema.encoding == "jsonschema":
                jsonschema.validate(msg, json.loads(schema.data))
            out["messages"].append(msg)
            out["log_times"].append(message.log_time)
        counts = {str(k): v for k, v in summary.statistics.channel_message_counts.items()}
    json.dump({"channels": channels, "counts": counts}, sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1])
