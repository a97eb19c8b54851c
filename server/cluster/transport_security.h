// How a cluster's front and shards protect the gRPC calls between them (server/README.md, "Operating a
// cluster"). A shard's gRPC port can change data (Add, Delete, PinStatistics, Backup), so it is guarded
// like the public HTTP API:
//   - a cluster key: the front sends `authorization: Bearer KEY` on every call; a shard with a key
//     refuses a call without it (UNAUTHENTICATED) or with another (PERMISSION_DENIED), compared in
//     constant time. The gRPC health service answers without it (it tells only whether the shard serves).
//   - TLS, from PEM files: the shard's certificate and key; optionally a CA whose certificates the shard
//     requires of its clients (mutual TLS). The front trusts the CA named in cluster.json (or the system's
//     roots) and may present its own certificate.
// A shard refuses to listen beyond loopback without a key (anyone who reaches the port could write);
// with a key but no TLS it warns that the key crosses the network in clear.
#pragma once

#include <memory>
#include <string>
#include <string_view>

#include "sift/base/error.h"

namespace grpc {
class ChannelCredentials;
class ServerCredentials;
class ServerContext;
class Status;
}  // namespace grpc

namespace oxbow::cluster {

// The metadata key (lowercase, as gRPC requires) and the value's prefix of the cluster key.
inline constexpr std::string_view kAuthorizationKey = "authorization";
inline constexpr std::string_view kBearerPrefix = "Bearer ";

// The shard's side (`oxbow serve --grpc-port` with --cluster-key, --grpc-tls-*).
struct ShardSecurity {
  std::string key;              // "" = calls need no key
  std::string tls_cert_file;    // PEM certificate chain; with tls_key_file, the port speaks TLS
  std::string tls_key_file;     // PEM private key
  std::string tls_client_ca_file;  // PEM CA certificates: clients must present a certificate signed by one

  bool tls() const { return !tls_cert_file.empty(); }
  // kInvalidArgument for a half-given pair or a client CA without TLS.
  [[nodiscard]] Status Check() const;
};

// The front's side (cluster.json "key_file" and "tls", or `serve --cluster --cluster-key`).
struct FrontSecurity {
  std::string key;              // sent on every call; "" = none
  bool tls = false;             // connect with TLS
  std::string tls_ca_file;      // PEM roots to trust; "" = the system's
  std::string tls_cert_file;    // PEM certificate chain the front presents (mutual TLS); "" = none
  std::string tls_key_file;     // its private key
  std::string tls_server_name;  // the name the shards' certificates carry, when not the replica's host
};

// gRPC credentials from the PEM files. kNotFound / kIoError naming an unreadable file.
[[nodiscard]] Result<std::shared_ptr<grpc::ServerCredentials>> MakeServerCredentials(const ShardSecurity& security);
[[nodiscard]] Result<std::shared_ptr<grpc::ChannelCredentials>> MakeChannelCredentials(const FrontSecurity& security);

// Whether a call carries the cluster key `key` (always true when `key` is empty); the refusal otherwise.
[[nodiscard]] grpc::Status Authorize(const grpc::ServerContext& context, const std::string& key);

// Whether binding `host` listens on loopback only (127.0.0.0/8, ::1, localhost).
bool IsLoopbackHost(std::string_view host);

// Reads a whole small file (a key or a PEM file); kNotFound when it cannot be read. `what` names it in the
// message ("the cluster key file").
[[nodiscard]] Result<std::string> ReadSmallFile(const std::string& path, std::string_view what);

}  // namespace oxbow::cluster
