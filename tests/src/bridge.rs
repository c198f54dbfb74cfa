//! A remote bridge's end of `Bridge.Attach` for tests that play the robot themselves: the hello first, then
//! whatever the test sends, with the server's downstream handed back to read.

use phone2act_proto::v1;
use phone2act_proto::v1::bridge_client::BridgeClient;
use tokio::sync::mpsc;

/// One upstream message.
pub fn upstream(message: v1::bridge_upstream::Message) -> v1::BridgeUpstream {
    v1::BridgeUpstream {
        message: Some(message),
    }
}

/// Opens `Bridge.Attach` on `channel` with `hello` as its first message. Returns the sender for the
/// bridge's later messages (a bounded queue of `queue`) and the server's downstream (welcome, commands).
pub async fn attach(
    channel: tonic::transport::Channel,
    hello: v1::BridgeHello,
    queue: usize,
) -> Result<
    (
        mpsc::Sender<v1::BridgeUpstream>,
        tonic::Streaming<v1::BridgeDownstream>,
    ),
    tonic::Status,
> {
    let (tx, rx) = mpsc::channel(queue);
    tx.send(upstream(v1::bridge_upstream::Message::Hello(hello)))
        .await
        .expect("the receiver is held until the call starts");
    let down = BridgeClient::new(channel)
        .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?
        .into_inner();
    Ok((tx, down))
}
