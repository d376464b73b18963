"""The contract between edge agents and the service: keys, messages, the watermark, the Zenoh session.

Below edge_agent/ and service/, above encoder_core/. The JSON Schemas of schemas/ ship inside it as
package data (fleet_wire.schemas) and are the published contract; docs/wire.md describes them.
"""
