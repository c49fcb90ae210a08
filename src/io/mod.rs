//! Bytes <-> messages. Owns MCAP reading ([`reader`]: streaming, chunk by chunk,
//! corrupt chunks named and truncated files read up to the damage) and writing
//! ([`writer`]: atomic, records copied unchanged, temporary files cleaned by [`cleanup`]), what each channel carries
//! ([`channels`]), the ROS wire formats ([`wire`]), point-cloud decoding ([`decoders`],
//! [`pointcloud`]) and the single encoding layer for every output channel
//! ([`encoders`]), and both ends of a conversion for evaluations and tests ([`roundtrip`]).
//! Knows MCAP, not GANs.

pub mod channels;
pub mod cleanup;
pub mod decoders;
pub mod encoders;
pub mod pointcloud;
pub mod reader;
pub mod roundtrip;
pub mod wire;
pub mod writer;

pub use channels::{ChannelEntry, ChannelTable};
pub use decoders::{CloudFormat, DecodedCloud, Family, decode_cloud};
pub use encoders::{Kind, Payload, PixelFormat, Transform};
pub use reader::{OnError, ReadReport, read_records};
pub use writer::{McapOutput, WriterSettings};
