// The checks of transport_security.h that need no gRPC (the command line runs them before it loads the
// cluster module, server/cli/modules/cluster_api.h).
#include <arpa/inet.h>

#include <string>

#include "server/cluster/transport_security.h"

namespace oxbow::cluster {

Status ShardSecurity::Check() const {
  if (tls_cert_file.empty() != tls_key_file.empty())
    return Fail(ErrorCode::kInvalidArgument, "TLS needs both a certificate and its private key (--grpc-tls-cert, --grpc-tls-key)");
  if (!tls_client_ca_file.empty() && !tls())
    return Fail(ErrorCode::kInvalidArgument, "--grpc-tls-client-ca needs TLS (--grpc-tls-cert, --grpc-tls-key)");
  return Ok();
}

bool IsLoopbackHost(std::string_view host) {
  if (host == "localhost" || host == "::1" || host == "[::1]") return true;
  in_addr v4{};
  const std::string text(host);
  if (inet_pton(AF_INET, text.c_str(), &v4) == 1) return (ntohl(v4.s_addr) >> 24) == 127;
  return false;
}

}  // namespace oxbow::cluster
